//! The sweep on a real Slurm: a 3-task array of short ablation runs on the embedded default scene,
//! submitted to a single-node Slurm that tools/slurm/test_array.sh starts (and stops) for the
//! test, gathered from the run folders, and compared with the same ablation run serially in one
//! process (`jobs::ablation::run`): every metric of every row must be equal, and so the tables
//! (wall times aside). Without Slurm installed the test is skipped with a message, except in CI
//! (`CI=true`), where it fails: `.ci/run` installs slurm-wlm and munge.

use std::io::Write;
use std::path::PathBuf;
use std::process::Command;

use anyhow::Result;
use reconstruct::fit::config::FitConfig;
use reconstruct::jobs::ablation::{self, AblationOptions};
use reconstruct::jobs::reconstruct::ReconstructOptions;
use reconstruct::jobs::sweep::{gather, manifest, plan};
use reconstruct::prior::source::PriorSource;
use reconstruct::scene::crate_dir;

fn installed(command: &str) -> bool {
    Command::new("sh").args(["-c", &format!("command -v {command}")]).output().map(|o| o.status.success()).unwrap_or(false)
}

/// The table without its last column (wall time, which no two runs share).
fn without_times(markdown: &str) -> String {
    markdown.lines().map(|l| if l.starts_with('|') { l.trim_end_matches('|').rsplit_once('|').map_or(l, |p| p.0) } else { l }).collect::<Vec<_>>().join("\n")
}

#[test]
fn slurm_array_gathers_to_the_serial_ablation_table() -> Result<()> {
    let missing: Vec<&str> = ["sbatch", "squeue", "scontrol", "slurmctld", "slurmd", "munged"].into_iter().filter(|c| !installed(c)).collect();
    if !missing.is_empty() {
        let msg = format!("{} not installed (apt-get install slurm-wlm munge; .ci/run does)", missing.join(", "));
        assert!(std::env::var("CI").as_deref() != Ok("true"), "the Slurm test cannot run in CI: {msg}");
        // Straight to stderr, past the test harness's capture, so the skip is seen.
        writeln!(std::io::stderr(), "Slurm test skipped: {msg}")?;
        return Ok(());
    }
    let dir = std::env::temp_dir().join(format!("reconstruct-sweep-slurm-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    // Short runs: a few iterations at 1 spp, one test view relit at 1 spp.
    let options = |out: PathBuf| AblationOptions {
        base: ReconstructOptions {
            auto_mode: true,
            eval_test_views: Some(1),
            progress: false,
            ..ReconstructOptions::new("default", FitConfig { iterations: 20, spp: 1, ..FitConfig::default() }, 1, out)
        },
        sources: vec![PriorSource::None, PriorSource::IdarbSim(1.0), PriorSource::Oracle],
        sweep: vec![],
    };
    let lines = plan::ablation(&options(dir.join("array")));
    assert_eq!(lines.len(), 3);
    plan::check_scenes(&lines)?;
    let path = dir.join("sweep.jsonl");
    manifest::write(&path, &lines, false)?;

    let run = Command::new("bash")
        .arg(crate_dir().join("tools/slurm/test_array.sh"))
        .arg(&path)
        .arg(env!("CARGO_BIN_EXE_reconstruct"))
        .arg("150")
        .output()?;
    let log = format!("{}{}", String::from_utf8_lossy(&run.stdout), String::from_utf8_lossy(&run.stderr));
    assert!(run.status.success(), "the Slurm array failed:\n{log}");
    println!("{}", log.lines().filter(|l| l.starts_with("submitted") || l.starts_with("array job")).collect::<Vec<_>>().join("\n"));

    let gathered = gather::gather(&lines)?;
    assert!(gathered.problems.is_empty(), "{:?}", gathered.problems);
    let (_, array) = &gathered.ablations[0];
    let serial = ablation::run(&options(dir.join("serial")))?;
    assert_eq!(array.rows.len(), 3);
    for (a, s) in array.rows.iter().zip(&serial.rows) {
        assert_eq!((&a.prior, &a.description), (&s.prior, &s.description));
        assert_eq!(a.evaluation, s.evaluation, "{}: the array's run differs from the serial one", a.prior);
    }
    let (a, s) = (without_times(&array.markdown()), without_times(&serial.markdown()));
    println!("{a}");
    assert_eq!(a, s);
    std::fs::remove_dir_all(&dir).ok();
    Ok(())
}
