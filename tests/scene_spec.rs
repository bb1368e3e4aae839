//! Scene spec files: the shipped hotdog spec, probe lookup with the fixture fallback, overrides.

mod common;

use std::path::PathBuf;

use reconstruct::scene::Switch;
use reconstruct::scene::{crate_dir, shared_dir, SceneSpec};

#[test]
fn the_hotdog_spec_names_the_shared_data_and_the_nerfactor_protocol() {
    let spec = SceneSpec::find("nerfactor_hotdog").unwrap();
    assert_eq!(spec.name, "nerfactor_hotdog");
    assert_eq!(spec.source, Some(crate_dir().join("scenes/nerfactor_hotdog.toml")));
    assert_eq!(spec.data_dir, shared_dir().join("data/nerfactor/hotdog_2163"));
    let train = spec.train_probe.clone().unwrap();
    assert_eq!((train.path.clone(), train.strength), (shared_dir().join("data/probes/2163.hdr"), 3.0));
    assert_eq!(spec.test_probes.names, ["city", "courtyard", "forest", "interior", "night", "studio", "sunrise", "sunset"]);
    assert_eq!(spec.test_probes.strength, 1.0);
    assert_eq!(spec.gt_dir(), Some(spec.data_dir.join("gt")));
    assert_eq!((spec.effects.shadows, spec.effects.specular), (Switch::Auto, Switch::Auto));
    // By path too, and the same result.
    assert_eq!(SceneSpec::find(crate_dir().join("scenes/nerfactor_hotdog.toml").to_str().unwrap()).unwrap(), spec);

    // The test probes are always available (the CC0 fixtures are the fallback).
    let probes = spec.load_test_probes().unwrap();
    assert_eq!(probes.len(), 8);
    for (p, name) in probes.iter().zip(&spec.test_probes.names) {
        assert_eq!(&p.name, name);
        assert_eq!((p.image.width, p.image.height, p.strength), (32, 16, 1.0));
    }

    if common::shared_data::require("scene_spec::the_hotdog_spec_names_the_shared_data_and_the_nerfactor_protocol").is_some() {
        let ds = spec.load_dataset().unwrap();
        assert_eq!(ds.train.len(), 100);
        let probe = spec.load_train_probe().unwrap();
        assert_eq!(probe.name, "2163");
        assert_eq!(probe.radiance_image().pixel(0, 5)[0], probe.image.pixel(0, 5)[0] * 3.0);
    }
}

#[test]
fn test_probes_fall_back_to_later_folders_and_missing_ones_are_named() {
    let dir = std::env::temp_dir().join(format!("reconstruct-spec-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("fallback.toml");
    std::fs::write(
        &file,
        r#"
        data = "data_here"
        [test_probes]
        names = ["forest", "nowhere"]
        folders = ["no_such_folder", "{crate}/tests/fixtures/probes"]
        strength = 2.5
        "#,
    )
    .unwrap();
    let spec = SceneSpec::load(&file).unwrap();
    assert_eq!(spec.name, "fallback");
    assert_eq!(spec.data_dir, dir.join("data_here"));
    assert_eq!(spec.test_probe_path("forest").unwrap(), crate_dir().join("tests/fixtures/probes/forest.hdr"));
    let msg = format!("{:#}", spec.test_probe_path("nowhere").unwrap_err());
    assert!(msg.contains("nowhere.hdr") && msg.contains("no_such_folder"), "{msg}");
    assert!(format!("{:#}", spec.load_test_probes().unwrap_err()).contains("nowhere"));
    assert!(format!("{:#}", spec.load_train_probe().unwrap_err()).contains("no training probe"));

    let moved = spec.clone().with_data_dir(PathBuf::from("/data/real_hotdog"));
    assert_eq!(moved.data_dir, PathBuf::from("/data/real_hotdog"));
    let msg = format!("{:#}", moved.load_dataset().unwrap_err());
    assert!(msg.contains("/data/real_hotdog") && msg.contains("fallback"), "{msg}");
}

#[test]
fn a_broken_spec_file_is_named() {
    let dir = std::env::temp_dir().join(format!("reconstruct-spec-bad-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("broken.toml");
    std::fs::write(&file, "data = \"x\"\n[effects]\nshadows = \"sometimes\"\n").unwrap();
    let msg = format!("{:#}", SceneSpec::load(&file).unwrap_err());
    assert!(msg.contains("broken.toml") && msg.contains("sometimes"), "{msg}");
    let msg = format!("{:#}", SceneSpec::find("/no/where/scene.toml").unwrap_err());
    assert!(msg.contains("/no/where/scene.toml"), "{msg}");
}
