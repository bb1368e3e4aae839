//! A Large Steps position update that never breaks the mesh, shared by the geometry pass and the
//! material pass's vertex refinement: the step is shortened (halved, up to 8 times) until no
//! triangle flips or collapses; if even 1/256 of it does, the caller gets the count of broken
//! triangles and stops with an error (it never carries on with a broken mesh).

use glam::DVec3;

use super::large_steps::LargeSteps;

/// Doubled triangle area, squared, below which a triangle of a mesh with mean edge `edge` counts
/// as degenerate: an area of 1e-6 of the edge squared, far below any triangle a remesh or a step
/// should leave, far above f32 round-off of the positions.
pub fn degenerate_area2(edge: f64) -> f64 {
    (1e-6 * edge * edge).powi(2)
}

/// Triangles the move from `a` to `b` breaks: whose orientation reversed, or whose area fell below
/// `min_area2` (twice the area, squared). A triangle already that small in `a` (a remesh can
/// leave a few needles) has no orientation to keep and counts only if it shrinks further.
pub fn broken_triangles(tris: &[[u32; 3]], a: &[[f64; 3]], b: &[[f64; 3]], min_area2: f64) -> usize {
    let n = |x: &[[f64; 3]], t: &[u32; 3]| {
        let p = t.map(|i| DVec3::from_array(x[i as usize]));
        (p[1] - p[0]).cross(p[2] - p[0])
    };
    tris.iter()
        .filter(|t| {
            let (na, nb) = (n(a, t), n(b, t));
            if !nb.is_finite() {
                return true;
            }
            if na.length_squared() < min_area2 {
                return nb.length_squared() < na.length_squared();
            }
            na.dot(nb) <= 0.0 || nb.length_squared() < min_area2
        })
        .count()
}

/// An accepted step: the new u and x = (I + λL)⁻¹u, and the share of the full step taken.
pub struct GuardedStep {
    pub u: Vec<[f64; 3]>,
    pub x: Vec<[f64; 3]>,
    pub share: f64,
}

/// Adds `du` to `u` (halving it while that breaks a triangle of `tris` at positions `x`); `Err`
/// carries the triangles even 1/256 of the step breaks.
pub fn guarded_step(ls: &LargeSteps, tris: &[[u32; 3]], x: &[[f64; 3]], u: &[[f64; 3]], du: &[[f64; 3]], min_area2: f64) -> Result<GuardedStep, usize> {
    let (mut share, mut broken) = (1.0, 0);
    for _ in 0..9 {
        let u_new: Vec<[f64; 3]> = u.iter().zip(du).map(|(a, d)| std::array::from_fn(|k| a[k] + share * d[k])).collect();
        let x_new = ls.solve(&u_new);
        broken = broken_triangles(tris, x, &x_new, min_area2);
        if broken == 0 {
            return Ok(GuardedStep { u: u_new, x: x_new, share });
        }
        share *= 0.5;
    }
    Err(broken)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_flip_is_counted_and_the_step_shortened() {
        // Two triangles of a unit square; moving vertex 2 across the diagonal flips triangle 0.
        let tris = [[0u32, 1, 2], [0, 2, 3]];
        let a = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]];
        let mut b = a;
        b[2] = [-0.2, -0.2, 0.0];
        assert_eq!(broken_triangles(&tris, &a, &b, degenerate_area2(1.0)), 2);
        b[2] = [0.9, 1.1, 0.0];
        assert_eq!(broken_triangles(&tris, &a, &b, degenerate_area2(1.0)), 0);
        // λ = 0: x = u. A step of −1.2 on vertex 2 flips; half of it (−0.6) does not.
        let ls = LargeSteps::new(4, &tris, 0.0).expect("system");
        let du = [[0.0; 3], [0.0; 3], [-1.2, -1.2, 0.0], [0.0; 3]];
        let step = guarded_step(&ls, &tris, &a, &ls.to_u(&a), &du, degenerate_area2(1.0)).expect("a shorter step is fine");
        assert_eq!(step.share, 0.5);
        assert!((step.x[2][0] - 0.4).abs() < 1e-9, "{:?}", step.x[2]);
        // Collapsing a triangle to a point at every scale of the step: refused.
        let far = [[0.0; 3], [0.0; 3], [-1e6, -1e6, 0.0], [0.0; 3]];
        assert!(guarded_step(&ls, &tris, &a, &ls.to_u(&a), &far, degenerate_area2(1.0)).is_err());
    }
}
