//! Bad values in well-formed files: NaN or Inf in a target image or a label map (refused, naming the
//! view, map and pixel, so no loss ever sees them; probes and meshes have their own tests beside their
//! loaders), a view whose mask is empty (skipped, and all empty refused), a view whose mask disagrees
//! with the known mesh (flagged beyond the stated share), and a full or unwritable checkpoint folder
//! (an error naming it, the last checkpoint intact).

use std::path::{Path, PathBuf};

use candle_core::{Device, Tensor};
use glam::{Quat, Vec3};
use reconstruct::fit::checkpoint::{self, Progress};
use reconstruct::fit::labels::PixelLabels;
use reconstruct::fit::training_view::TrainingView;
use reconstruct::fit::view_screening::{screen_views, MAX_SILHOUETTE_DISAGREEMENT};
use reconstruct::geometry::bvh::Bvh;
use reconstruct::geometry::primitives::MeshBuilder;
use reconstruct::geometry::Mesh;
use reconstruct::image::Image;
use reconstruct::material::{BaseColor, PartMaterial, Scalar};
use reconstruct::optim::adam::AdamState;
use reconstruct::prior::view_labels::ViewLabels;
use reconstruct::render::gbuffer::GBuffer;
use reconstruct::scene::Camera;

const SIZE: usize = 32;

fn sphere() -> (Mesh, Bvh) {
    let mut b = MeshBuilder::new();
    let p = b.part(PartMaterial { name: "m".into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) });
    b.ellipsoid(p, Vec3::ZERO, Vec3::ONE, Quat::IDENTITY, 24, 12);
    let mesh = b.build();
    let bvh = Bvh::build(&mesh);
    (mesh, bvh)
}

fn camera() -> Camera {
    Camera::look_at(Vec3::new(0.0, -4.0, 0.5), Vec3::ZERO, Vec3::Z, 0.8, SIZE, SIZE)
}

/// An RGBA target whose alpha is the mesh's own coverage shifted `shift` pixels to the right.
fn target(mesh: &Mesh, bvh: &Bvh, cam: &Camera, shift: usize) -> Image {
    let covered: Vec<bool> = GBuffer::trace(mesh, bvh, cam).surfels.iter().map(Option::is_some).collect();
    let mut img = Image::new(SIZE, SIZE, 4);
    for y in 0..SIZE {
        for x in shift..SIZE {
            let a = if covered[y * SIZE + x - shift] { 1.0 } else { 0.0 };
            img.pixel_mut(x, y).copy_from_slice(&[0.5, 0.4, 0.3, a]);
        }
    }
    img
}

#[test]
fn nan_or_inf_in_a_target_image_is_refused_naming_the_view_and_pixel() {
    let (mesh, bvh) = sphere();
    let cam = camera();
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        let mut img = target(&mesh, &bvh, &cam, 0);
        img.pixel_mut(7, 3)[1] = bad;
        let msg = format!("{:#}", TrainingView::from_image("train_042", &cam, 0, &img, &mesh, &bvh).err().expect("refused"));
        assert!(msg.contains("train_042") && msg.contains("pixel (7, 3) channel 1") && msg.contains(&bad.to_string()), "{msg}");
    }
}

#[test]
fn nan_in_a_label_map_is_refused_naming_the_view_map_and_pixel() {
    let (mesh, bvh) = sphere();
    let cam = camera();
    let view = TrainingView::from_image("train_007", &cam, 0, &target(&mesh, &bvh, &cam, 0), &mesh, &bvh).expect("test setup");
    let good = || ViewLabels {
        albedo: Image::filled(SIZE, SIZE, &[0.5, 0.5, 0.5]),
        normal: Image::filled(SIZE, SIZE, &[0.5, 0.5, 1.0]),
        metallic: Image::filled(SIZE, SIZE, &[0.0]),
        roughness: Image::filled(SIZE, SIZE, &[0.5]),
        mask: Image::filled(SIZE, SIZE, &[1.0]),
    };
    assert!(PixelLabels::gather(&good(), &view.pixels, SIZE, SIZE, cam.c2w, "train_007").is_ok());
    for (map, bad) in [("albedo", f32::NAN), ("roughness", f32::INFINITY), ("normal", f32::NAN)] {
        let mut labels = good();
        let img = match map {
            "albedo" => &mut labels.albedo,
            "roughness" => &mut labels.roughness,
            _ => &mut labels.normal,
        };
        img.pixel_mut(30, 2)[0] = bad;
        let msg = format!("{:#}", PixelLabels::gather(&labels, &view.pixels, SIZE, SIZE, cam.c2w, "train_007").err().expect("refused"));
        assert!(msg.contains("train_007") && msg.contains(map) && msg.contains("pixel (30, 2)"), "{msg}");
    }
}

#[test]
fn a_view_with_an_empty_mask_is_skipped_and_all_empty_is_refused() {
    let (mesh, bvh) = sphere();
    let cam = camera();
    let seen = target(&mesh, &bvh, &cam, 0);
    let mut empty = seen.clone();
    empty.data.chunks_exact_mut(4).for_each(|p| p[3] = 0.0);
    let views: Vec<TrainingView> = [("train_000", &seen), ("train_001", &empty), ("train_002", &seen)]
        .iter()
        .enumerate()
        .map(|(i, (name, img))| TrainingView::from_image(name, &cam, i, img, &mesh, &bvh).expect("test setup"))
        .collect();
    assert_eq!(views[1].mask_pixels, 0);
    let kept = screen_views(views.clone(), true, "tiny").expect("one empty view is skipped");
    assert_eq!(kept.iter().map(|v| (v.name.as_str(), v.index)).collect::<Vec<_>>(), [("train_000", 0), ("train_002", 2)]);
    let all_empty: Vec<TrainingView> = vec![views[1].clone(), views[1].clone()];
    let msg = format!("{:#}", screen_views(all_empty, true, "tiny").err().expect("refused"));
    assert!(msg.contains("tiny") && msg.contains("every training view's mask is empty"), "{msg}");
}

/// The mesh and a mask that is its own silhouette agree; the same mask moved 4 pixels (a camera off
/// by about 6° here: the focal length is 38 pixels) disagrees beyond the stated share, which is what
/// triggers the warning.
#[test]
fn a_mask_that_disagrees_with_the_known_mesh_is_flagged_beyond_the_stated_share() {
    let (mesh, bvh) = sphere();
    let cam = camera();
    let agree = TrainingView::from_image("agree", &cam, 0, &target(&mesh, &bvh, &cam, 0), &mesh, &bvh).expect("test setup");
    let off = TrainingView::from_image("off", &cam, 1, &target(&mesh, &bvh, &cam, 4), &mesh, &bvh).expect("test setup");
    println!("disagreement: aligned {:.3}, shifted 4 px {:.3} (warning above {MAX_SILHOUETTE_DISAGREEMENT})", agree.silhouette_disagreement, off.silhouette_disagreement);
    assert_eq!(agree.silhouette_disagreement, 0.0);
    assert!(off.silhouette_disagreement > MAX_SILHOUETTE_DISAGREEMENT, "{}", off.silhouette_disagreement);
    // Flagged views are warned about, not dropped.
    assert_eq!(screen_views(vec![agree, off], true, "tiny").expect("kept").len(), 2);
}

fn tmp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("reconstruct-bad-values-{tag}-{}", std::process::id()));
    std::fs::remove_dir_all(&d).ok();
    std::fs::create_dir_all(&d).expect("test setup");
    d
}

fn save(dir: &Path, kd: f32) -> anyhow::Result<()> {
    let dev = Device::Cpu;
    let t = |n: usize, v: f32| Tensor::full(v, (n, 1, 3), &dev).expect("test setup");
    let adam = AdamState { step: 0, slots: Vec::new() };
    let mut progress = Progress {
        iteration: 0,
        state_file: String::new(),
        identity: serde_json::json!({ "kd": kd }),
        history: Vec::new(),
        adam_step: 0,
        adam_slots: Vec::new(),
    };
    checkpoint::save(dir, &t(4, kd), &t(4, 0.5), &t(6, 1.0), &adam, Vec::new(), &mut progress)
}

/// A full disk: every temporary file the checkpoint writer may create is a link to /dev/full, whose
/// writes fail with "no space left on device" (root ignores permission bits, so a read-only folder would
/// not stop this test's writes). The save fails naming the folder, and the previous checkpoint loads
/// unchanged. A run folder that cannot be created (a file is in the way) is named too.
#[test]
fn a_full_or_unwritable_checkpoint_folder_is_named_and_the_last_checkpoint_stays_intact() {
    let dir = tmp("full").join("checkpoint");
    save(&dir, 0.25).expect("first checkpoint");
    let files: Vec<PathBuf> = std::fs::read_dir(&dir).expect("test setup").filter_map(|e| e.ok()).map(|e| e.path()).collect();
    for f in &files {
        std::os::unix::fs::symlink("/dev/full", reconstruct::atomic_write::partial_path(f)).expect("test setup");
    }
    let err = save(&dir, 0.75).expect_err("a full disk must fail the save (are the temporary names still atomic_write::partial_path?)");
    let msg = format!("{err:#}");
    assert!(msg.contains(&dir.display().to_string()), "{msg}");
    let cp = checkpoint::load(&dir).expect("the last checkpoint still loads").expect("and is there");
    assert_eq!(cp.progress.identity, serde_json::json!({ "kd": 0.25 }));
    assert_eq!(cp.kd.flatten_all().and_then(|t| t.to_vec1::<f32>()).expect("f32"), vec![0.25; 12]);

    let blocked = tmp("blocked");
    std::fs::write(blocked.join("run"), "a file where the run folder should be").expect("test setup");
    let msg = format!("{:#}", save(&blocked.join("run/checkpoint"), 0.5).expect_err("refused"));
    assert!(msg.contains(&blocked.join("run/checkpoint").display().to_string()), "{msg}");
}
