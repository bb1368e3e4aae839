//! Which training views the fit uses, decided once they are traced: a view whose mask is empty does
//! not show the object, so it is skipped with a warning (all empty is an error); with known geometry,
//! a view whose mask and the mesh's silhouette disagree by more than [`MAX_SILHOUETTE_DISAGREEMENT`]
//! is named in a warning (a wrong camera, a wrong mesh, or a mask that is not the object's).

use anyhow::{bail, Result};

use super::training_view::TrainingView;

pub use crate::scene::dataset::MASK_THRESHOLD;

/// Largest share of silhouette pixels (mesh ∪ mask) on which the two may disagree before a warning.
/// Disagreement is counted with a one-pixel tolerance (a pixel counts only when no pixel of the other
/// silhouette lies in its 3×3 neighbourhood), so the half-pixel jitter of an anti-aliased outline
/// against the mesh's one ray per pixel never counts, at any resolution; what remains comes from shape
/// or pose errors. Measured: the shared hotdog's ground-truth mesh scores 0 on all 100 training views
/// (at full size and at 1/4). 5 % is a sliver a few pixels wide along the outline of an object 200
/// pixels across, well beyond rounding, small enough to catch a camera off by a degree or two.
pub const MAX_SILHOUETTE_DISAGREEMENT: f32 = 0.05;

/// Share of the union of two silhouettes (`mesh[i]`, `alpha[i] ≥ MASK_THRESHOLD`, row-major
/// `width`×`height`) on which they disagree beyond one pixel (see [`MAX_SILHOUETTE_DISAGREEMENT`]).
/// 0 when both are empty.
pub fn silhouette_disagreement(mesh: &[bool], alpha: &[f32], width: usize, height: usize) -> f32 {
    let mask: Vec<bool> = alpha.iter().map(|&a| a >= MASK_THRESHOLD).collect();
    let near = |set: &[bool], x: usize, y: usize| {
        (y.saturating_sub(1)..(y + 2).min(height)).any(|yy| (x.saturating_sub(1)..(x + 2).min(width)).any(|xx| set[yy * width + xx]))
    };
    let (mut union, mut disagree) = (0usize, 0usize);
    for y in 0..height {
        for x in 0..width {
            let i = y * width + x;
            if !(mesh[i] || mask[i]) {
                continue;
            }
            union += 1;
            if (mesh[i] && !near(&mask, x, y)) || (mask[i] && !near(mesh, x, y)) {
                disagree += 1;
            }
        }
    }
    if union == 0 {
        0.0
    } else {
        disagree as f32 / union as f32
    }
}

/// The views the fit uses: those with something in their mask. Warns (stderr) about the skipped ones
/// and, when `known_geometry`, about views whose silhouette disagreement exceeds
/// [`MAX_SILHOUETTE_DISAGREEMENT`]. Errors, naming the scene, when every mask is empty.
pub fn screen_views(views: Vec<TrainingView>, known_geometry: bool, scene: &str) -> Result<Vec<TrainingView>> {
    let total = views.len();
    let (kept, empty): (Vec<TrainingView>, Vec<TrainingView>) = views.into_iter().partition(|v| v.mask_pixels > 0);
    if kept.is_empty() && total > 0 {
        bail!("scene {scene:?}: every training view's mask is empty (alpha < {MASK_THRESHOLD} everywhere), so no view shows the object");
    }
    if !empty.is_empty() {
        let names: Vec<&str> = empty.iter().map(|v| v.name.as_str()).collect();
        eprintln!(
            "warning: scene {scene:?}: skipping {} of {total} training views whose mask is empty (the object is not in them): {}",
            empty.len(),
            names.join(", ")
        );
    }
    if known_geometry {
        let off: Vec<String> = kept
            .iter()
            .filter(|v| v.silhouette_disagreement > MAX_SILHOUETTE_DISAGREEMENT)
            .map(|v| format!("{} ({:.1} %)", v.name, 100.0 * v.silhouette_disagreement))
            .collect();
        if !off.is_empty() {
            eprintln!(
                "warning: scene {scene:?}: in {} of {} training views the mesh's silhouette and the mask disagree on more than {:.0} % of their pixels \
                 (wrong camera, wrong mesh, or a mask that is not the object's): {}",
                off.len(),
                kept.len(),
                100.0 * MAX_SILHOUETTE_DISAGREEMENT,
                off.join(", ")
            );
        }
    }
    Ok(kept)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn disc(width: usize, height: usize, cx: f32, cy: f32, r: f32) -> Vec<bool> {
        (0..width * height)
            .map(|i| {
                let (x, y) = ((i % width) as f32 + 0.5, (i / width) as f32 + 0.5);
                (x - cx).powi(2) + (y - cy).powi(2) <= r * r
            })
            .collect()
    }

    fn alpha(set: &[bool]) -> Vec<f32> {
        set.iter().map(|&b| if b { 1.0 } else { 0.0 }).collect()
    }

    #[test]
    fn one_pixel_of_outline_jitter_is_not_disagreement_but_a_shifted_silhouette_is() {
        let (w, h) = (64, 64);
        let mesh = disc(w, h, 32.0, 32.0, 20.0);
        assert_eq!(silhouette_disagreement(&mesh, &alpha(&mesh), w, h), 0.0);
        // A slightly larger mask (anti-aliased outline rounded the other way): within a pixel.
        assert_eq!(silhouette_disagreement(&mesh, &alpha(&disc(w, h, 32.0, 32.0, 20.9)), w, h), 0.0);
        // Shifted by 6 pixels (a camera off by about that much): a crescent on each side.
        let shifted = silhouette_disagreement(&mesh, &alpha(&disc(w, h, 38.0, 32.0, 20.0)), w, h);
        assert!(shifted > MAX_SILHOUETTE_DISAGREEMENT, "{shifted}");
        // Disjoint: everything disagrees; both empty: nothing.
        assert_eq!(silhouette_disagreement(&disc(w, h, 10.0, 10.0, 5.0), &alpha(&disc(w, h, 50.0, 50.0, 5.0)), w, h), 1.0);
        assert_eq!(silhouette_disagreement(&vec![false; w * h], &vec![0.0; w * h], w, h), 0.0);
    }
}
