//! The runs of a study share a preparation exactly when their geometry is the same. With a
//! reconstruction whose pass holds the normals to the labels, each prior gets its own geometry
//! (pass recorded with its weight, kept in the run's folder), and the run without a prior gets one
//! without the prior (kept in the study's folder); a second run of a prior already prepared reuses
//! it. With the pass's prior off, one geometry serves every prior, and it is the very one the
//! unlabelled run saved: the identity of a pass without the prior did not change.

use anyhow::Result;
use reconstruct::fit::config::FitConfig;
use reconstruct::fit::geometry_pass::GeometryPassConfig;
use reconstruct::jobs::geometry_cache::GEOMETRY_FILE;
use reconstruct::jobs::reconstruct::{GeometrySource, ReconstructOptions};
use reconstruct::jobs::shared_preparation::SharedPreparation;
use reconstruct::prior::source::PriorSource;

#[test]
fn a_prior_that_shapes_the_geometry_gets_a_preparation_of_its_own() -> Result<()> {
    let tmp = std::env::temp_dir().join(format!("reconstruct-shared-prep-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&tmp);
    let mut base = ReconstructOptions::new("default", FitConfig { texture_res: 64, ..FitConfig::default() }, 1, tmp.clone());
    base.geometry = GeometrySource::Reconstruct;
    // A short pass: which geometry is made, and where it is kept, is what matters here.
    base.geometry_pass = GeometryPassConfig { iterations: 12, batch: 2, ..GeometryPassConfig::default() };
    base.progress = false;
    let row = |base: &ReconstructOptions, prior: &PriorSource| ReconstructOptions { out: tmp.join(prior.tag().replace(':', "_")), ..base.clone() };
    let priors = [PriorSource::None, PriorSource::IdarbSim(1.0), PriorSource::Oracle];

    let mut shared = SharedPreparation::new(&tmp);
    let mut weights = Vec::new();
    for prior in &priors {
        let prepared = shared.get(&row(&base, prior), prior)?;
        weights.push(prepared.geometry.pass.as_ref().expect("a reconstruction records its pass").config.normal_prior);
    }
    assert_eq!(shared.count(), 3);
    let w = base.geometry_pass.normal_prior;
    assert!(w > 0.0);
    assert_eq!(weights, vec![0.0, w, w], "the pass as it ran: the prior only with labels");
    assert!(tmp.join(GEOMETRY_FILE).is_file(), "the unlabelled geometry is the study's");
    for prior in &priors[1..] {
        assert!(row(&base, prior).out.join(GEOMETRY_FILE).is_file(), "{} keeps its own geometry", prior.tag());
    }
    shared.get(&row(&base, &priors[1]), &priors[1])?;
    assert_eq!(shared.count(), 3, "a prior already prepared is reused");

    // The pass's prior off: one preparation for all, reusing the unlabelled geometry on disk.
    let saved = std::fs::metadata(tmp.join(GEOMETRY_FILE))?.modified()?;
    let mut off = base.clone();
    off.geometry_pass.normal_prior = 0.0;
    let mut shared = SharedPreparation::new(&tmp);
    for prior in &priors {
        shared.get(&row(&off, prior), prior)?;
    }
    assert_eq!(shared.count(), 1);
    assert_eq!(std::fs::metadata(tmp.join(GEOMETRY_FILE))?.modified()?, saved, "the saved geometry is reused, not remade");
    std::fs::remove_dir_all(&tmp).ok();
    Ok(())
}
