//! The guard between an optimiser's proposed vertex move and the mesh: no step may flip a triangle
//! or shrink one to a degenerate sliver, because such a mesh must never reach the BVH. Shared by
//! the geometry pass and the material pass's vertex refinement.
//!
//! Positions are stepped in Large Steps' u = (I + λL)x (`optim::large_steps`). Given the current
//! x and u and a proposed step du, [`guard_step`] returns the positions to take, trying in turn:
//! 1. the full step;
//! 2. the full step with the vertices of the triangles it breaks **held back** (kept where they
//!    are, repeated until no triangle breaks), when that holds few vertices. A remesh can leave an
//!    isolated sliver that any step shrinks further; shortening the whole step cannot clear it,
//!    holding its three vertices does, while the rest of the mesh moves on;
//! 3. the step halved, up to 1/256 of it, each time with the hold-back of 2;
//!    otherwise the caller stops with an error (the mesh is collapsing as a whole).
//!
//! A held-back step changes x at a few vertices only, so u is recomputed from the accepted x
//! (u = (I + λL)x) to keep the two consistent.

use glam::DVec3;

use super::large_steps::LargeSteps;

/// Holding back is for isolated slivers: when more than this share of the vertices would have to
/// stay, the step as a whole is too long and it is halved instead. One vertex in a hundred is
/// far above the few needles a remesh leaves (`geometry_pass` tolerates 1 degenerate triangle in
/// 1000) and far below a mesh-wide collapse.
const MAX_HELD_SHARE: f64 = 0.01;

/// Halvings tried after the full step: down to 1/256 of it.
const HALVINGS: usize = 8;

/// Doubled triangle area, squared, below which a triangle of a mesh with mean edge `edge` counts
/// as degenerate: an area of 1e-6 of the edge squared, far below any triangle a remesh or a step
/// should leave, far above f32 round-off of the positions.
pub fn degenerate_area2(edge: f64) -> f64 {
    (1e-6 * edge * edge).powi(2)
}

/// Triangles the move from `a` to `b` breaks: whose orientation reversed, or whose area fell below
/// `min_area2` (twice the area, squared). A triangle already that small in `a` (a remesh can
/// leave a few needles) has no orientation to keep and counts only if it shrinks further.
pub fn broken_triangles(tris: &[[u32; 3]], a: &[[f64; 3]], b: &[[f64; 3]], min_area2: f64) -> Vec<usize> {
    let n = |x: &[[f64; 3]], t: &[u32; 3]| {
        let p = t.map(|i| DVec3::from_array(x[i as usize]));
        (p[1] - p[0]).cross(p[2] - p[0])
    };
    tris.iter()
        .enumerate()
        .filter(|(_, t)| {
            let (na, nb) = (n(a, t), n(b, t));
            if !nb.is_finite() {
                return true;
            }
            if na.length_squared() < min_area2 {
                return nb.length_squared() < na.length_squared();
            }
            na.dot(nb) <= 0.0 || nb.length_squared() < min_area2
        })
        .map(|(i, _)| i)
        .collect()
}

/// The move from `x` to `x_new` with the vertices of broken triangles reset to `x`, repeated until
/// no triangle breaks. Returns the number of vertices held, or `None` when more than `max_held`
/// would be. Terminates: every round holds at least one more vertex, or none is broken (a
/// triangle whose vertices are all held is unchanged, hence not broken).
fn hold_back(tris: &[[u32; 3]], x: &[[f64; 3]], x_new: &mut [[f64; 3]], min_area2: f64, max_held: usize) -> Option<usize> {
    let mut held = vec![false; x.len()];
    let mut count = 0;
    loop {
        let broken = broken_triangles(tris, x, x_new, min_area2);
        if broken.is_empty() {
            return Some(count);
        }
        for t in broken {
            for &v in &tris[t] {
                let v = v as usize;
                if !held[v] {
                    held[v] = true;
                    count += 1;
                    x_new[v] = x[v];
                }
            }
        }
        if count > max_held {
            return None;
        }
    }
}

/// An accepted position step.
#[derive(Clone, Debug)]
pub struct GuardedStep {
    pub u: Vec<[f64; 3]>,
    pub x: Vec<[f64; 3]>,
    /// Share of the proposed step taken (1, ½, ¼, ...).
    pub share: f64,
    /// Vertices held where they were.
    pub held: usize,
}

/// What the guard found when no step could be taken: the triangles the smallest share still broke.
#[derive(Clone, Debug)]
pub struct Collapse {
    pub broken: usize,
}

/// The step to take from (`u`, `x`) along `du` (see the module comment), or the collapse.
pub fn guard_step(
    ls: &LargeSteps,
    tris: &[[u32; 3]],
    u: &[[f64; 3]],
    x: &[[f64; 3]],
    du: &[[f64; 3]],
    min_area2: f64,
) -> std::result::Result<GuardedStep, Collapse> {
    let max_held = (MAX_HELD_SHARE * x.len() as f64) as usize;
    let mut share = 1.0;
    let mut broken = 0;
    for _ in 0..=HALVINGS {
        let u_new: Vec<[f64; 3]> = u.iter().zip(du).map(|(a, d)| std::array::from_fn(|k| a[k] + share * d[k])).collect();
        let mut x_new = ls.solve(&u_new);
        let first = broken_triangles(tris, x, &x_new, min_area2);
        if first.is_empty() {
            return Ok(GuardedStep { u: u_new, x: x_new, share, held: 0 });
        }
        broken = first.len();
        if let Some(held) = hold_back(tris, x, &mut x_new, min_area2, max_held) {
            let u_held = ls.to_u(&x_new);
            return Ok(GuardedStep { u: u_held, x: x_new, share, held });
        }
        share *= 0.5;
    }
    Err(Collapse { broken })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A flat n×n grid of vertices at unit spacing (counter-clockwise triangles seen from +z).
    fn grid(n: u32) -> (Vec<[f64; 3]>, Vec<[u32; 3]>) {
        let mut x = Vec::new();
        for j in 0..n {
            for i in 0..n {
                x.push([i as f64, j as f64, 0.0]);
            }
        }
        let mut t = Vec::new();
        for j in 0..n - 1 {
            for i in 0..n - 1 {
                let a = j * n + i;
                t.push([a, a + 1, a + n + 1]);
                t.push([a, a + n + 1, a + n]);
            }
        }
        (x, t)
    }

    fn normal_z(x: &[[f64; 3]], t: &[u32; 3]) -> f64 {
        let p = t.map(|i| DVec3::from_array(x[i as usize]));
        (p[1] - p[0]).cross(p[2] - p[0]).z
    }

    #[test]
    fn a_flip_is_found_and_a_rigid_move_is_not() {
        let (x, t) = grid(3);
        let moved: Vec<[f64; 3]> = x.iter().map(|p| [p[0] + 0.3, p[1] - 0.2, p[2] + 1.0]).collect();
        assert!(broken_triangles(&t, &x, &moved, 1e-12).is_empty());
        let mut flipped = x.clone();
        flipped[4] = [2.6, 2.6, 0.0]; // the centre past the far corner: its triangles turn over
        let b = broken_triangles(&t, &x, &flipped, 1e-12);
        assert!(!b.is_empty());
        for &i in &b {
            assert!(t[i].contains(&4), "only triangles at the moved vertex can break");
        }
    }

    #[test]
    fn a_sliver_that_any_step_shrinks_is_held_while_the_rest_moves() -> anyhow::Result<()> {
        // Vertex 1 is moved almost onto the line from vertex 0 to vertex n + 1, so triangle 0
        // (0, 1, n + 1) is a sliver (its doubled area ~1e-7, below the threshold). The step translates every
        // vertex and moves vertex 1 further towards that line: the sliver shrinks at every share,
        // so halving alone cannot clear it.
        let (mut x, t) = grid(20);
        x[1] = [0.5, 0.5 - 1e-7, 0.0];
        let min_area2 = 1e-12;
        let area2 = |x: &[[f64; 3]]| normal_z(x, &t[0]).powi(2);
        assert!(area2(&x) < min_area2, "the set-up must start with a sliver");
        let ls = LargeSteps::new(x.len(), &t, 0.0)?;
        let u = ls.to_u(&x);
        let mut du = vec![[0.1, 0.0, 0.0]; x.len()];
        du[1] = [0.1, 0.5e-7, 0.0];
        let step = guard_step(&ls, &t, &u, &x, &du, min_area2).map_err(|c| anyhow::anyhow!("collapse: {c:?}"))?;
        assert_eq!(step.share, 1.0, "the rest of the mesh takes the full step");
        assert!(step.held >= 3 && step.held < x.len(), "held {}", step.held);
        assert!(broken_triangles(&t, &x, &step.x, min_area2).is_empty());
        // Unheld vertices moved by the full step; held ones did not move.
        let moved = (0..x.len()).filter(|&v| (step.x[v][0] - x[v][0] - 0.1).abs() < 1e-9).count();
        let still = (0..x.len()).filter(|&v| step.x[v] == x[v]).count();
        assert_eq!(moved + still, x.len());
        assert_eq!(still, step.held);
        // u is consistent with the accepted x.
        let back = ls.solve(&step.u);
        for (a, b) in back.iter().zip(&step.x) {
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1e-9);
            }
        }
        Ok(())
    }

    #[test]
    fn a_step_that_turns_the_whole_mesh_over_is_shortened_and_a_broken_step_is_a_collapse() -> anyhow::Result<()> {
        // Mirroring every vertex through the plane x = 9.5 reverses every triangle at shares past
        // ½ (and flattens them at ½); holding more than 1 % of the vertices is refused, so the
        // guard shortens the step instead and takes ¼ of it.
        let (x, t) = grid(20);
        let ls = LargeSteps::new(x.len(), &t, 0.0)?;
        let u = ls.to_u(&x);
        let du: Vec<[f64; 3]> = x.iter().map(|p| [2.0 * (9.5 - p[0]), 0.0, 0.0]).collect();
        let step = guard_step(&ls, &t, &u, &x, &du, 1e-12).map_err(|c| anyhow::anyhow!("collapse: {c:?}"))?;
        assert!(step.share == 0.25 && step.held == 0, "share {} held {}", step.share, step.held);
        for tri in &t {
            assert!(normal_z(&step.x, tri) > 0.0);
        }
        // A step that is non-finite everywhere breaks every triangle at every share: a collapse.
        let nan = vec![[f64::NAN, 0.0, 0.0]; x.len()];
        let c = guard_step(&ls, &t, &u, &x, &nan, 1e-12).err().ok_or_else(|| anyhow::anyhow!("NaN step accepted"))?;
        assert_eq!(c.broken, t.len());
        Ok(())
    }
}
