//! The visible surface point of a pixel as a differentiable function of the mesh: what the
//! geometry pass needs to move vertices from the shading of covered pixels (issue "geometry from
//! the images", source (a) of position gradients).
//!
//! Each covered pixel keeps its primary ray (origin o, direction d) and the triangle the ray hit;
//! both are fixed for the step (the G-buffer's discrete choice carries no gradient; silhouettes
//! are handled by `silhouette_op`). Everything else is recomputed from the current vertex
//! positions, so it moves with them:
//! - the hit (t, b1, b2) solves  o + t·d = p0 + b1·(p1 − p0) + b2·(p2 − p0)  (Möller–Trumbore);
//! - the shading normal n = normalize(b0·N0 + b1·N1 + b2·N2) from the vertex normals;
//! - per-vertex attributes (the pass's material) a = b0·A0 + b1·A1 + b2·A2.
//!
//! Adjoint of the hit: with M = [−d | p1 − p0 | p2 − p0] and x = (t, b1, b2), M·x = o − p0, so
//! dx = −M⁻¹ · Σ bᵢ dpᵢ and ∂L/∂pᵢ = −bᵢ · M⁻ᵀ ∂L/∂x. The vertex normals are an input (from
//! `vertex_normals_op`), so their own dependence on the positions is that operator's business.
//!
//! Inputs (all f32 or all f64): positions [V, 3], vertex normals [V, 3], vertex attributes
//! [V, K]. Output [N, 3 + K]: normal, then attributes, one row per covered pixel. Arithmetic is
//! f64 inside whatever the tensor type.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::{DMat3, DVec3};
use rayon::prelude::*;

use crate::optim::tape::{apply, Kernel, Real};

/// A covered pixel's fixed data: its primary ray and the triangle it hit.
#[derive(Clone, Copy, Debug)]
pub struct PixelRay {
    pub origin: DVec3,
    pub dir: DVec3,
    pub triangle: u32,
}

/// The surface-point operator of one set of pixel rays over one triangle list.
pub struct SurfacePoints {
    pub rays: Arc<[PixelRay]>,
    pub triangles: Arc<[[u32; 3]]>,
}

/// One pixel's hit with what both passes need.
struct Hit {
    corners: [usize; 3],
    /// (b0, b1, b2).
    bary: [f64; 3],
    /// M = [−d | e1 | e2].
    m: DMat3,
}

fn vec3<T: Real>(data: &[T], i: usize) -> DVec3 {
    DVec3::new(data[3 * i].to_f64(), data[3 * i + 1].to_f64(), data[3 * i + 2].to_f64())
}

impl SurfacePoints {
    fn hit<T: Real>(&self, k: usize, positions: &[T]) -> Hit {
        let ray = self.rays[k];
        let corners = self.triangles[ray.triangle as usize].map(|i| i as usize);
        let [p0, p1, p2] = corners.map(|i| vec3(positions, i));
        let m = DMat3::from_cols(-ray.dir, p1 - p0, p2 - p0);
        // The solve extends past the triangle's edges analytically (no clamping), so finite
        // differences and the adjoint see one smooth function.
        let x = m.inverse() * (ray.origin - p0);
        Hit { corners, bary: [1.0 - x.y - x.z, x.y, x.z], m }
    }
}

impl Kernel for SurfacePoints {
    fn name(&self) -> &'static str {
        "surface-points"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        let ok = shapes.len() == 3
            && shapes[0].len() == 2
            && shapes[0][1] == 3
            && shapes[1] == shapes[0]
            && shapes[2].len() == 2
            && shapes[2][0] == shapes[0][0];
        if !ok {
            return Err(candle_core::Error::Msg(format!(
                "surface-points: expected positions [V,3], normals [V,3], attributes [V,K], got {shapes:?}"
            )));
        }
        let v = shapes[0][0];
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&i| i as usize >= v)) {
            return Err(candle_core::Error::Msg(format!("surface-points: triangle {t:?} indexes past {v} vertices")));
        }
        Ok(vec![self.rays.len(), 3 + shapes[2][1]])
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (positions, normals, attrs) = (x[0], x[1], x[2]);
        let k_attr = shapes[2][1];
        out.par_chunks_mut(3 + k_attr).enumerate().for_each(|(k, row)| {
            let h = self.hit(k, positions);
            let m: DVec3 = (0..3).map(|c| h.bary[c] * vec3(normals, h.corners[c])).sum();
            let n = m.normalize_or_zero();
            for c in 0..3 {
                row[c] = T::from_f64(n[c]);
            }
            for j in 0..k_attr {
                let v: f64 = (0..3).map(|c| h.bary[c] * attrs[k_attr * h.corners[c] + j].to_f64()).sum();
                row[3 + j] = T::from_f64(v);
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let (positions, normals, attrs) = (x[0], x[1], x[2]);
        let k_attr = shapes[2][1];
        let stride = 3 + k_attr;
        // Per pixel: gradients of its three corners' position, normal and attributes, computed in
        // parallel, then accumulated in pixel order (deterministic, no races).
        let per_pixel: Vec<(Hit, [DVec3; 3], DVec3, Vec<f64>)> = (0..self.rays.len())
            .into_par_iter()
            .map(|k| {
                let h = self.hit(k, positions);
                let gk = &g[stride * k..stride * (k + 1)];
                let g_n = DVec3::new(gk[0].to_f64(), gk[1].to_f64(), gk[2].to_f64());
                let vn = h.corners.map(|i| vec3(normals, i));
                let m: DVec3 = (0..3).map(|c| h.bary[c] * vn[c]).sum();
                let len = m.length();
                // normalize's adjoint: (g − n (n·g)) / |m|; zero where the normals cancel.
                let g_m = if len > 0.0 {
                    let n = m / len;
                    (g_n - n * n.dot(g_n)) / len
                } else {
                    DVec3::ZERO
                };
                let g_a: Vec<f64> = gk[3..].iter().map(|v| v.to_f64()).collect();
                // ∂L/∂b_c through the normal and the attributes.
                let g_b: [f64; 3] = std::array::from_fn(|c| {
                    let attr: f64 = (0..k_attr).map(|j| g_a[j] * attrs[k_attr * h.corners[c] + j].to_f64()).sum();
                    g_m.dot(vn[c]) + attr
                });
                // b0 = 1 − b1 − b2, so x = (t, b1, b2) sees (0, g_b1 − g_b0, g_b2 − g_b0).
                let g_x = DVec3::new(0.0, g_b[1] - g_b[0], g_b[2] - g_b[0]);
                let y = h.m.transpose().inverse() * g_x;
                let g_p = h.bary.map(|b| -b * y);
                (h, g_p, g_m, g_a)
            })
            .collect();
        let [g_pos, g_nrm, g_attr] = grads else { unreachable!("three inputs") };
        for (h, g_p, g_m, g_a) in &per_pixel {
            for ((&i, &b), g_pc) in h.corners.iter().zip(&h.bary).zip(g_p) {
                if let Some(gp) = g_pos.as_deref_mut() {
                    for a in 0..3 {
                        gp[3 * i + a] += T::from_f64(g_pc[a]);
                    }
                }
                if let Some(gn) = g_nrm.as_deref_mut() {
                    for a in 0..3 {
                        gn[3 * i + a] += T::from_f64(b * g_m[a]);
                    }
                }
                if let Some(ga) = g_attr.as_deref_mut() {
                    for j in 0..k_attr {
                        ga[k_attr * i + j] += T::from_f64(b * g_a[j]);
                    }
                }
            }
        }
        Ok(())
    }
}

/// Normal and attributes at every pixel ray's hit, [N, 3 + K], on the tape.
pub fn surface_points(op: SurfacePoints, positions: &Tensor, normals: &Tensor, attributes: &Tensor) -> Result<Tensor> {
    apply(op, &[positions, normals, attributes])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    /// A test mesh: flat positions, normals and attributes (per vertex), and its triangles.
    type TestMesh = (Vec<f64>, Vec<f64>, Vec<f64>, Arc<[[u32; 3]]>);

    /// Two triangles of a bent quad and rays through both, seen from +z.
    fn quad() -> TestMesh {
        let positions = vec![-1.0, -1.0, 0.1, 1.0, -1.0, -0.2, 1.0, 1.0, 0.3, -1.0, 1.0, 0.0];
        let normals = vec![0.1, 0.0, 1.0, 0.0, 0.2, 1.0, -0.3, 0.1, 1.0, 0.0, 0.0, 1.0];
        let attrs = vec![0.2, 0.9, 0.4, 0.1, 0.7, 0.5, 0.3, 0.3];
        (positions, normals, attrs, vec![[0, 1, 2], [0, 2, 3]].into())
    }

    fn rays(points: &[(f64, f64, u32)]) -> Arc<[PixelRay]> {
        let origin = DVec3::new(0.1, -0.2, 5.0);
        points
            .iter()
            .map(|&(x, y, triangle)| PixelRay { origin, dir: (DVec3::new(x, y, 0.0) - origin).normalize(), triangle })
            .collect()
    }

    fn check(points: &[(f64, f64, u32)]) -> anyhow::Result<()> {
        let (p, n, a, tris) = quad();
        let d = &Device::Cpu;
        let inputs = [Tensor::from_vec(p, (4, 3), d)?, Tensor::from_vec(n, (4, 3), d)?, Tensor::from_vec(a, (4, 2), d)?];
        let rays = rays(points);
        let report = check_gradient(
            |x| surface_points(SurfacePoints { rays: rays.clone(), triangles: tris.clone() }, &x[0], &x[1], &x[2]),
            &inputs,
            1e-6,
            1e-5,
        )?;
        println!("{report}");
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        check(&[(0.5, -0.3, 0), (0.2, 0.6, 1), (-0.4, 0.1, 1), (0.9, 0.1, 0)])
    }

    #[test]
    fn gradients_hold_at_hard_cases() -> anyhow::Result<()> {
        // A hit on the shared diagonal, one next to a vertex, one at a corner of the quad.
        check(&[(0.0, 0.0, 0), (0.999, -0.999, 0), (-0.98, 0.98, 1)])?;
        // A grazing triangle: the ray nearly parallel to its plane.
        let d = &Device::Cpu;
        let positions = Tensor::from_vec(vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 1.0f64], (3, 3), d)?;
        let normals = Tensor::from_vec(vec![0.0, 1.0, 0.0, 0.1, 1.0, 0.0, 0.0, 1.0, 0.1f64], (3, 3), d)?;
        let attrs = Tensor::from_vec(vec![0.1, 0.5, 0.9f64], (3, 1), d)?;
        let origin = DVec3::new(-3.0, 0.05, 0.3);
        let rays: Arc<[PixelRay]> =
            vec![PixelRay { origin, dir: (DVec3::new(0.3, 0.0, 0.3) - origin).normalize(), triangle: 0 }].into();
        let tris: Arc<[[u32; 3]]> = vec![[0, 1, 2]].into();
        check_gradient(
            |x| surface_points(SurfacePoints { rays: rays.clone(), triangles: tris.clone() }, &x[0], &x[1], &x[2]),
            &[positions, normals, attrs],
            1e-7,
            1e-4,
        )?;
        Ok(())
    }

    #[test]
    fn forward_interpolates_at_the_hit() -> anyhow::Result<()> {
        // A flat triangle in z = 0 seen straight down: the hit's barycentrics are the point's.
        let d = &Device::Cpu;
        let positions = Tensor::from_vec(vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0f64], (3, 3), d)?;
        let normals = Tensor::from_vec(vec![0.0, 0.0, 1.0, 0.0, 0.0, 1.0, 0.0, 0.0, 1.0f64], (3, 3), d)?;
        let attrs = Tensor::from_vec(vec![0.0, 1.0, 2.0f64], (3, 1), d)?;
        let rays: Arc<[PixelRay]> =
            vec![PixelRay { origin: DVec3::new(0.25, 0.5, 2.0), dir: DVec3::NEG_Z, triangle: 0 }].into();
        let out = surface_points(SurfacePoints { rays, triangles: vec![[0, 1, 2]].into() }, &positions, &normals, &attrs)?;
        let row = out.flatten_all()?.to_vec1::<f64>()?;
        // b1 = 0.25, b2 = 0.5 → attribute 0·0.25 + 1·0.25 + 2·0.5 = 1.25.
        assert!((row[2] - 1.0).abs() < 1e-12 && (row[3] - 1.25).abs() < 1e-12, "{row:?}");
        Ok(())
    }
}
