//! The tests that read the shared data folder (`../shared`, or `$RECONSTRUCT_SHARED_DIR`): one registry
//! of what each needs, and the one call each makes before reading it.
//!
//! Where the data is present they run. Where it is absent, [`require`] names the test and the missing
//! paths on stderr (past the harness's capture) and the test returns early; `tests/shared_data.rs`
//! prints one summary line listing every test that skips. With `RECONSTRUCT_REQUIRE_SHARED=1` (CI
//! sets it: CI has the data) a skip is a failure instead, in the test itself and in the summary.

use std::io::Write;
use std::path::PathBuf;

pub use reconstruct::scene::shared_dir;

/// Set to 1 to make every skip for missing shared data a failure.
pub const REQUIRE_ENV: &str = "RECONSTRUCT_REQUIRE_SHARED";

const HOTDOG: &str = "data/nerfactor/hotdog_2163/transforms_train.json";
const HOTDOG_GT: &str = "data/nerfactor/hotdog_2163/gt/hotdog.obj";
const HOTDOG_DEPTH: &str = "data/nerfactor/hotdog_2163/train_000/depth.exr";
const PROBE_2163: &str = "data/probes/2163.hdr";
const PROBE_CITY: &str = "data/probes/city.hdr";

/// Every test that needs shared data ("file::test") and the paths (under the shared folder) it reads.
pub const NEEDS: &[(&str, &[&str])] = &[
    ("atlas_hotdog::hotdog_atlas_and_baked_ground_truth", &[HOTDOG_GT]),
    ("gbuffer_dataset::gbuffer_matches_dataset_ground_truth_passes", &[HOTDOG, HOTDOG_GT]),
    ("geometry_hotdog_gt::hotdog_ground_truth_matches_readme_and_materials_json", &[HOTDOG_GT]),
    ("geometry_hotdog_gt::plain_obj_loader_reads_the_mtl_like_materials_json", &[HOTDOG_GT]),
    ("geometry_metrics_hotdog::hotdog_ground_truth_against_itself (ignored by default)", &[HOTDOG, HOTDOG_GT]),
    ("idarb_keys::full_unet_requests_exactly_the_official_keys_and_shapes", &["idarb/unet_keys_full.txt", "idarb/unet_config_full.json"]),
    ("idarb_keys::full_vae_has_the_sd_layout", &["idarb/vae_config_full.json"]),
    ("idarb_schedule::schedule_matches_official_table", &["idarb/scheduler_table.json"]),
    ("light_probe_2163::readme_probe_values_and_orientation", &[PROBE_2163]),
    ("light_probe_2163::light_pipeline_on_the_real_probe", &[PROBE_2163]),
    ("metrics_protocol::albedo_scale_undoes_a_known_gain_on_the_first_val_view", &[HOTDOG]),
    ("metrics_protocol::relit_ground_truth_over_white_has_a_white_background", &[HOTDOG]),
    ("prior_sim_calibration::level_one_matches_idarbs_published_accuracy_on_the_hotdog", &[HOTDOG]),
    ("render_hotdog::ground_truth_render_matches_dataset_per_view", &[HOTDOG, HOTDOG_GT, PROBE_2163]),
    ("render_hotdog::probe_orientation_agrees_with_relit_ground_truth", &[HOTDOG, HOTDOG_GT, PROBE_2163, PROBE_CITY]),
    ("scene_hotdog::hotdog_has_the_documented_views_sizes_and_files", &[HOTDOG]),
    ("scene_hotdog::metadata_repeats_the_transforms", &[HOTDOG]),
    ("scene_hotdog::cameras_sit_on_the_documented_sphere_and_look_at_the_origin", &[HOTDOG]),
    ("scene_hotdog::depth_back_projects_into_the_scene_box_and_projects_back_to_its_pixel", &[HOTDOG]),
    ("scene_hotdog::gt_mesh_vertices_project_onto_the_silhouette_and_behind_the_visible_depth", &[HOTDOG, HOTDOG_GT]),
    ("scene_hotdog::ground_truth_maps_decode_to_sensible_values", &[HOTDOG]),
    ("scene_io::the_cc0_fixture_probes_are_16x32_positive_radiance (byte copies of the shared probes)", &[PROBE_CITY]),
    ("scene_io::training_probe_2163_matches_the_readme_values", &[PROBE_2163]),
    ("scene_io::a_shared_depth_map_reads_as_one_channel", &[HOTDOG_DEPTH]),
    ("scene_spec::the_hotdog_spec_names_the_shared_data_and_the_nerfactor_protocol", &[HOTDOG, PROBE_2163]),
];

/// Whether skips are failures (`RECONSTRUCT_REQUIRE_SHARED=1`).
pub fn required() -> bool {
    std::env::var(REQUIRE_ENV).is_ok_and(|v| v == "1")
}

/// The registered paths of `test` that are missing.
pub fn missing(test: &str) -> Vec<PathBuf> {
    let Some((_, paths)) = NEEDS.iter().find(|(t, _)| *t == test) else {
        panic!("{test} reads shared data but is not listed in tests/common/shared_data.rs NEEDS");
    };
    paths.iter().map(|p| shared_dir().join(p)).filter(|p| !p.exists()).collect()
}

/// The shared folder when everything `test` (its `NEEDS` entry) reads is there. Otherwise the skip is
/// named on stderr and None returned, or, with `RECONSTRUCT_REQUIRE_SHARED=1`, the test fails.
pub fn require(test: &str) -> Option<PathBuf> {
    let missing = missing(test);
    if missing.is_empty() {
        return Some(shared_dir());
    }
    let list = missing.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ");
    assert!(!required(), "{test}: shared data missing ({list}) but {REQUIRE_ENV}=1: a skip is a failure here");
    // Straight to stderr, past the harness's capture, so the skip is seen.
    let _ = writeln!(std::io::stderr(), "skipped {test}: shared data missing ({list}; set RECONSTRUCT_SHARED_DIR)");
    None
}
