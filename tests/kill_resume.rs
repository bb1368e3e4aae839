//! Kill anywhere, rerun, same result: the `reconstruct` binary on the embedded default scene (tiny
//! settings) is killed with SIGKILL at several points, started again with the same command, and
//! must end with the same report.json as an uninterrupted run (wall times aside). The kill points
//! are found by watching the run folder and the run's stderr, never by sleeping:
//! - after the first checkpoint (`checkpoint/progress.json` appears), known geometry;
//! - during the evaluation (the `evaluating` line), known geometry;
//! - inside the geometry pass (the `visual hull:` line, which the pass follows; checked afterwards
//!   that the pass's result was not saved yet), reconstructed geometry;
//! - after the geometry pass's result was saved (`geometry.json` appears), reconstructed geometry:
//!   the rerun must reuse it and still match.
//!
//! A rerun with one setting changed into the same folder is refused, naming the setting.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use serde_json::Value;

const BIN: &str = env!("CARGO_BIN_EXE_reconstruct");

/// Longest a single run may take before the test gives up (a hang, not a timing assertion).
const RUN_LIMIT: Duration = Duration::from_secs(900);

fn command(out: &Path, geometry: &str, extra: &[&str]) -> Command {
    let mut c = Command::new(BIN);
    c.args(["--scene", "default", "--geometry", geometry, "--mode", "mc", "--spp", "1", "--iterations", "40", "--checkpoint-every", "8"]);
    c.args(["--batch", "1", "--texture-res", "128", "--light-res", "8", "--eval-spp", "1", "--eval-test-views", "2"]);
    c.args(["--geometry-iterations", "30", "--prior", "idarb-sim", "--labelled-views", "5"]);
    c.args(extra).arg("--out").arg(out);
    c.stdout(Stdio::null()).stderr(Stdio::piped());
    c
}

/// Runs to the end; returns stderr (panics, with it, on failure).
fn run(out: &Path, geometry: &str, extra: &[&str]) -> String {
    let o = command(out, geometry, extra).output().expect("start the binary");
    let err = String::from_utf8_lossy(&o.stderr).into_owned();
    assert!(o.status.success(), "run into {} failed:\n{err}", out.display());
    err
}

/// Starts a run and SIGKILLs it as soon as `point` holds (given the run folder and the stderr lines
/// so far). Panics when the run ends first.
fn kill_at(out: &Path, geometry: &str, what: &str, point: impl Fn(&Path, &[String]) -> bool) {
    let mut child = command(out, geometry, &[]).spawn().expect("start the binary");
    let lines = Arc::new(Mutex::new(Vec::<String>::new()));
    let reader = {
        let (stderr, lines) = (child.stderr.take().expect("piped"), lines.clone());
        std::thread::spawn(move || BufReader::new(stderr).lines().map_while(Result::ok).for_each(|l| lines.lock().expect("lock").push(l)))
    };
    let start = Instant::now();
    loop {
        if point(out, &lines.lock().expect("lock")) {
            child.kill().expect("SIGKILL"); // std's kill sends SIGKILL on Unix
            child.wait().expect("reap");
            break;
        }
        if let Some(status) = child.try_wait().expect("poll") {
            panic!("the run ended ({status}) before the kill point {what}:\n{}", lines.lock().expect("lock").join("\n"));
        }
        assert!(start.elapsed() < RUN_LIMIT, "kill point {what} never reached");
        std::thread::sleep(Duration::from_millis(5));
    }
    reader.join().expect("stderr reader");
}

/// report.json without wall times: keys `seconds`, `stage_seconds`, `timings`, `phases` at any depth, and
/// durations written into text (the visual hull's summary says "sampled in 0.48 s, total 0.81 s").
fn comparable(out: &Path) -> Value {
    let duration = regex::Regex::new(r"[0-9]+(\.[0-9]+)? s\b").expect("pattern");
    let strip_text = |v: &mut Value| {
        if let Value::String(t) = v {
            *t = duration.replace_all(t, "… s").into_owned();
        }
    };
    fn strip(v: &mut Value, text: &dyn Fn(&mut Value)) {
        text(v);
        match v {
            Value::Object(m) => {
                for k in ["seconds", "stage_seconds", "timings", "phases"] {
                    m.remove(k);
                }
                m.values_mut().for_each(|x| strip(x, text));
            }
            Value::Array(a) => a.iter_mut().for_each(|x| strip(x, text)),
            _ => {}
        }
    }
    let path = out.join("report.json");
    let text = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut v: Value = serde_json::from_str(&text).expect("report.json parses");
    strip(&mut v, &strip_text);
    v
}

fn assert_same(reference: &Value, out: &Path, what: &str) {
    let got = comparable(out);
    if &got != reference {
        let diffs = reconstruct::fit::settings_diff::differences(reference, &got);
        panic!("after a kill {what} and a rerun, report.json differs from the uninterrupted run's:\n{}", diffs.iter().take(20).map(|d| d.to_string()).collect::<Vec<_>>().join("\n"));
    }
}

fn temp() -> PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-kill-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

#[test]
fn killed_runs_rerun_to_the_uninterrupted_report() {
    let dir = temp();
    let has_line = |prefix: &'static str| move |_: &Path, lines: &[String]| lines.iter().any(|l| l.starts_with(prefix));

    // Known geometry.
    run(&dir.join("gt"), "gt", &[]);
    let reference = comparable(&dir.join("gt"));
    // Deterministic: a second uninterrupted run gives the same report.
    run(&dir.join("gt-again"), "gt", &[]);
    assert_same(&reference, &dir.join("gt-again"), "(none: a second uninterrupted run)");

    let out = dir.join("gt-checkpoint");
    kill_at(&out, "gt", "after the first checkpoint", |out, _| out.join("checkpoint/progress.json").is_file());
    let err = run(&out, "gt", &[]);
    assert!(err.contains("resuming from"), "the rerun must resume:\n{err}");
    assert_same(&reference, &out, "after the first checkpoint");

    let out = dir.join("gt-evaluation");
    kill_at(&out, "gt", "during the evaluation", has_line("evaluating"));
    assert!(!out.join("report.json").exists());
    run(&out, "gt", &[]);
    assert_same(&reference, &out, "during the evaluation");

    // A changed setting into the same folder is refused, naming it, old and new.
    let o = command(&out, "gt", &["--seed", "3"]).output().expect("start the binary");
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("training.fit.seed: 0 → 3") && err.contains(&out.display().to_string()), "{err}");

    // Reconstructed geometry.
    run(&dir.join("rec"), "reconstruct", &[]);
    let reference = comparable(&dir.join("rec"));

    let out = dir.join("rec-pass");
    kill_at(&out, "reconstruct", "inside the geometry pass", has_line("visual hull:"));
    assert!(!out.join("geometry.json").exists(), "killed after the geometry pass had finished: the kill point was missed");
    run(&out, "reconstruct", &[]);
    assert_same(&reference, &out, "inside the geometry pass");

    let out = dir.join("rec-saved");
    kill_at(&out, "reconstruct", "after the geometry was saved", |out, _| out.join("geometry.json").is_file());
    let err = run(&out, "reconstruct", &[]);
    assert!(err.contains("reusing the reconstruction"), "the rerun must reuse the saved geometry:\n{err}");
    assert_same(&reference, &out, "after the geometry was saved");
    std::fs::remove_dir_all(&dir).ok();
}
