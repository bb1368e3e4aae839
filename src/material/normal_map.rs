//! A tangent-space normal map on the UV atlas, as NVDiffRecMC learns in its second pass: each texel
//! holds a unit vector m (z ≥ 0) in the surface's MikkTSpace frame (`geometry::tangents`), and the
//! shading normal at a point is normalize(m.x·T + m.y·B + m.z·N), with N the interpolated (two-sided)
//! shading normal, T the interpolated corner tangent and B = s·(N × T). m = (0, 0, 1) leaves N alone.
//!
//! It gives the shading the detail a mesh at the geometry pass's resolution cannot hold (creases,
//! the rim of a plate): the learned mesh's normals are what limit relighting on learned geometry
//! (docs/geometry.md). The same formula runs in two places, side by side here: [`perturb`] for the
//! renderer (G-buffers, bounce hits) and [`perturb_on_tape`] for the optimiser, whose gradient
//! reaches the map through candle's autodiff.

use std::sync::Arc;

use candle_core::{Tensor, D};
use glam::{Vec2, Vec3, Vec4};

use crate::geometry::tangents::interpolate;
use crate::image::Image;
use crate::material::texture_maps::sample_atlas;

/// Per-channel bounds of a texel, NVDiffRecMC's `nrm_min`/`nrm_max`: the tilt may go any way, but
/// the vector never points into the surface.
pub const NORMAL_MIN: [f64; 3] = [-1.0, -1.0, 0.0];
pub const NORMAL_MAX: [f64; 3] = [1.0, 1.0, 1.0];

#[derive(Clone, Debug, PartialEq)]
pub struct NormalMap {
    /// Tangent-space unit vectors, [res, res, 3], row 0 at the top (v = 1), like the kd texture.
    pub map: Image,
    /// MikkTSpace frame of each corner of the atlas mesh's triangles (`geometry::tangents`).
    pub tangents: Arc<[[Vec4; 3]]>,
}

impl NormalMap {
    /// The map that changes nothing: (0, 0, 1) everywhere.
    pub fn flat(res: usize, tangents: Arc<[[Vec4; 3]]>) -> NormalMap {
        NormalMap { map: Image::filled(res, res, &[0.0, 0.0, 1.0]), tangents }
    }

    /// The texel vector at atlas UV `uv` (bilinear, as the kd and ks textures are looked up).
    pub fn lookup(&self, uv: Vec2) -> Vec3 {
        let mut m = [0.0f32; 3];
        sample_atlas(&self.map, uv, &mut m);
        Vec3::from_array(m)
    }

    /// The shading normal at barycentrics `bary` of `triangle`, atlas UV `uv`, where the mesh's own
    /// shading normal is `normal`.
    pub fn shading_normal(&self, triangle: u32, bary: Vec3, uv: Vec2, normal: Vec3) -> Vec3 {
        match self.tangents.get(triangle as usize) {
            Some(corners) => {
                let (t, s) = interpolate(corners, bary);
                perturb(normal, t, s, self.lookup(uv))
            }
            None => normal,
        }
    }

    /// Each texel rescaled to unit length (after an optimiser step; NVDiffRecMC does the same). A
    /// texel of zero length becomes (0, 0, 1).
    pub fn normalize_texels(data: &mut [f32]) {
        for m in data.chunks_exact_mut(3) {
            let v = Vec3::new(m[0], m[1], m[2]).try_normalize().unwrap_or(Vec3::Z);
            m.copy_from_slice(&v.to_array());
        }
    }
}

/// normalize(m.x·T + m.y·s·(N × T) + m.z·N); N itself when that vector vanishes.
pub fn perturb(normal: Vec3, tangent: Vec3, sign: f32, m: Vec3) -> Vec3 {
    let bitangent = sign * normal.cross(tangent);
    (m.x * tangent + m.y * bitangent + m.z * normal).try_normalize().unwrap_or(normal)
}

/// [`perturb`] on the tape, row by row: `normal` [N, 3] (constant or on the tape), `tangent` and
/// `bitangent` [N, 3] constants (the bitangent s·(N × T) of the normal's value), `m` [N, 3] the
/// map's lookups. The gradient reaches `m` (and `normal`, through its m.z·N term).
pub fn perturb_on_tape(normal: &Tensor, tangent: &Tensor, bitangent: &Tensor, m: &Tensor) -> candle_core::Result<Tensor> {
    let mx = m.narrow(D::Minus1, 0, 1)?;
    let my = m.narrow(D::Minus1, 1, 1)?;
    let mz = m.narrow(D::Minus1, 2, 1)?;
    let v = ((tangent.broadcast_mul(&mx)? + bitangent.broadcast_mul(&my)?)? + normal.broadcast_mul(&mz)?)?;
    // m.z ≥ 0 and |m| = 1 keep |v| well away from 0 for the frames the renderer builds; the floor
    // only keeps a pathological row finite.
    let len = v.sqr()?.sum_keepdim(D::Minus1)?.affine(1.0, 1e-20)?.sqrt()?;
    v.broadcast_div(&len)
}

/// The constants [`perturb_on_tape`] needs for shading points given as (triangle, barycentrics,
/// shading normal): rows of the tangent and of the bitangent s·(N × T), flattened.
pub fn frames_at(tangents: &[[Vec4; 3]], points: impl Iterator<Item = (u32, Vec3, Vec3)>) -> (Vec<f32>, Vec<f32>) {
    let (mut t_rows, mut b_rows) = (Vec::new(), Vec::new());
    for (triangle, bary, normal) in points {
        let (t, s) = tangents.get(triangle as usize).map_or((normal.any_orthonormal_vector(), 1.0), |c| interpolate(c, bary));
        t_rows.extend_from_slice(&t.to_array());
        b_rows.extend_from_slice(&(s * normal.cross(t)).to_array());
    }
    (t_rows, b_rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::Sampler;
    use candle_core::{Device, Var};

    fn random_unit(rng: &mut Sampler) -> Vec3 {
        loop {
            let v = Vec3::new(rng.next_f32(), rng.next_f32(), rng.next_f32()) * 2.0 - Vec3::ONE;
            if v.length() > 0.2 && v.length() < 1.0 {
                return v.normalize();
            }
        }
    }

    #[test]
    fn flat_texel_keeps_the_normal_and_a_tilt_turns_it_toward_the_tangent() {
        let (n, t) = (Vec3::Z, Vec3::X);
        assert!((perturb(n, t, 1.0, Vec3::Z) - n).length() < 1e-6);
        let tilted = perturb(n, t, 1.0, Vec3::new(1.0, 0.0, 1.0).normalize());
        assert!((tilted - Vec3::new(1.0, 0.0, 1.0).normalize()).length() < 1e-6);
        // +y tilts toward +v: B = s·(N × T) = +y for s = 1, −y for s = −1.
        assert!(perturb(n, t, 1.0, Vec3::new(0.0, 0.6, 0.8)).y > 0.5);
        assert!(perturb(n, t, -1.0, Vec3::new(0.0, 0.6, 0.8)).y < -0.5);
    }

    /// The tape's forward equals `perturb`, and its gradient in m and in N matches central
    /// differences of `perturb`, at random frames and texels (and near-grazing tilts).
    #[test]
    fn tape_matches_perturb_and_its_gradient_matches_finite_differences() -> anyhow::Result<()> {
        let dev = Device::Cpu;
        let mut rng = Sampler::new(7, 0);
        let rows = 24;
        let (mut n, mut t, mut b, mut m, mut w) = (vec![], vec![], vec![], vec![], vec![]);
        let mut cases = Vec::new();
        for k in 0..rows {
            let normal = random_unit(&mut rng);
            // An interpolated tangent: near-orthogonal, not unit.
            let tangent = (random_unit(&mut rng).reject_from(normal).normalize() + 0.05 * random_unit(&mut rng)) * 0.9;
            let sign = if k % 2 == 0 { 1.0 } else { -1.0 };
            let mut texel = random_unit(&mut rng);
            texel.z = texel.z.abs().max(if k % 5 == 0 { 0.02 } else { 0.1 });
            let texel = texel.normalize();
            let weight = random_unit(&mut rng);
            n.extend(normal.to_array());
            t.extend(tangent.to_array());
            b.extend((sign * normal.cross(tangent)).to_array());
            m.extend(texel.to_array());
            w.extend(weight.to_array());
            cases.push((normal, tangent, sign, texel, weight));
        }
        let nv = Var::from_vec(n, (rows, 3), &dev)?;
        let mv = Var::from_vec(m, (rows, 3), &dev)?;
        let tt = Tensor::from_vec(t, (rows, 3), &dev)?;
        let bt = Tensor::from_vec(b, (rows, 3), &dev)?;
        let wt = Tensor::from_vec(w, (rows, 3), &dev)?;
        let out = perturb_on_tape(nv.as_tensor(), &tt, &bt, mv.as_tensor())?;
        let rows_out = out.to_vec2::<f32>()?;
        for (k, (normal, tangent, sign, texel, _)) in cases.iter().enumerate() {
            let want = perturb(*normal, *tangent, *sign, *texel);
            assert!((Vec3::from_slice(&rows_out[k]) - want).length() < 1e-5, "row {k}");
        }
        let grads = (out * &wt)?.sum_all()?.backward()?;
        let gm = grads.get(mv.as_tensor()).expect("m gradient").to_vec2::<f32>()?;
        let gn = grads.get(nv.as_tensor()).expect("normal gradient").to_vec2::<f32>()?;
        let h = 1e-3f64;
        for (k, (normal, tangent, sign, texel, weight)) in cases.iter().enumerate() {
            // The bitangent is a constant of the normal's value on the tape: hold it here too.
            let b = *sign * normal.cross(*tangent);
            let f = |nn: glam::DVec3, mm: glam::DVec3| -> f64 {
                let v = mm.x * tangent.as_dvec3() + mm.y * b.as_dvec3() + mm.z * nn;
                v.normalize().dot(weight.as_dvec3())
            };
            for c in 0..3 {
                let mut e = glam::DVec3::ZERO;
                e[c] = h;
                let fd_m = (f(normal.as_dvec3(), texel.as_dvec3() + e) - f(normal.as_dvec3(), texel.as_dvec3() - e)) / (2.0 * h);
                let fd_n = (f(normal.as_dvec3() + e, texel.as_dvec3()) - f(normal.as_dvec3() - e, texel.as_dvec3())) / (2.0 * h);
                assert!((gm[k][c] as f64 - fd_m).abs() < 2e-3 * (1.0 + fd_m.abs()), "row {k} m[{c}]: tape {} fd {fd_m}", gm[k][c]);
                assert!((gn[k][c] as f64 - fd_n).abs() < 2e-3 * (1.0 + fd_n.abs()), "row {k} n[{c}]: tape {} fd {fd_n}", gn[k][c]);
            }
        }
        Ok(())
    }

    #[test]
    fn normalize_texels_makes_unit_vectors_and_repairs_zero_ones() {
        let mut d = vec![0.0, 0.0, 2.0, 3.0, 0.0, 4.0, 0.0, 0.0, 0.0];
        NormalMap::normalize_texels(&mut d);
        assert_eq!(&d[0..3], &[0.0, 0.0, 1.0]);
        assert!((d[3] - 0.6).abs() < 1e-6 && (d[5] - 0.8).abs() < 1e-6);
        assert_eq!(&d[6..9], &[0.0, 0.0, 1.0]);
    }
}
