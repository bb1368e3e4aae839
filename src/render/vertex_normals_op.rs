//! Area-weighted vertex normals as a differentiable function of the vertex positions, so the
//! geometry pass's shading normals move with the mesh (the same rule as
//! `Mesh::area_weighted_normals`: each face adds its edge cross product, |c| = 2·area).
//!
//! Forward: m_v = Σ_{faces f ∋ v} c_f with c_f = (p1 − p0) × (p2 − p0); N_v = m_v / |m_v|
//! (+z where no face contributes, like the mesh's rule, with zero gradient).
//! Backward: ∂L/∂m_v = (g − N (N·g)) / |m_v|; every face gathers ∂L/∂c_f = Σ_{v ∈ f} ∂L/∂m_v, and
//! the cross product's adjoint sends e2 × g_c to p1, g_c × e1 to p2 and minus their sum to p0.
//!
//! Input positions [V, 3] (f32 or f64), output [V, 3].

use std::sync::Arc;

use candle_core::{Result, Tensor};
use glam::DVec3;

use crate::optim::tape::{apply, Kernel, Real};

pub struct VertexNormals {
    pub triangles: Arc<[[u32; 3]]>,
}

fn vec3<T: Real>(data: &[T], i: usize) -> DVec3 {
    DVec3::new(data[3 * i].to_f64(), data[3 * i + 1].to_f64(), data[3 * i + 2].to_f64())
}

impl VertexNormals {
    /// Unnormalised sums m_v.
    fn sums<T: Real>(&self, positions: &[T]) -> Vec<DVec3> {
        let mut m = vec![DVec3::ZERO; positions.len() / 3];
        for t in self.triangles.iter() {
            let [a, b, c] = t.map(|i| i as usize);
            let (p0, p1, p2) = (vec3(positions, a), vec3(positions, b), vec3(positions, c));
            let n = (p1 - p0).cross(p2 - p0);
            for i in [a, b, c] {
                m[i] += n;
            }
        }
        m
    }
}

impl Kernel for VertexNormals {
    fn name(&self) -> &'static str {
        "vertex-normals"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        let s = shapes[0];
        if shapes.len() != 1 || s.len() != 2 || s[1] != 3 {
            return Err(candle_core::Error::Msg(format!("vertex-normals: expected positions [V, 3], got {shapes:?}")));
        }
        if let Some(t) = self.triangles.iter().find(|t| t.iter().any(|&i| i as usize >= s[0])) {
            return Err(candle_core::Error::Msg(format!("vertex-normals: triangle {t:?} indexes past {} vertices", s[0])));
        }
        Ok(s.to_vec())
    }

    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        for (v, m) in self.sums(x[0]).into_iter().enumerate() {
            let n = m.try_normalize().unwrap_or(DVec3::Z);
            for a in 0..3 {
                out[3 * v + a] = T::from_f64(n[a]);
            }
        }
        Ok(())
    }

    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gp) = grads[0].as_deref_mut() else { return Ok(()) };
        let positions = x[0];
        let g_m: Vec<DVec3> = self
            .sums(positions)
            .into_iter()
            .enumerate()
            .map(|(v, m)| {
                let len = m.length();
                if len > 0.0 && len.is_finite() {
                    let n = m / len;
                    let gv = vec3(g, v);
                    (gv - n * n.dot(gv)) / len
                } else {
                    DVec3::ZERO
                }
            })
            .collect();
        for t in self.triangles.iter() {
            let [a, b, c] = t.map(|i| i as usize);
            let (p0, p1, p2) = (vec3(positions, a), vec3(positions, b), vec3(positions, c));
            let (e1, e2) = (p1 - p0, p2 - p0);
            let g_c = g_m[a] + g_m[b] + g_m[c];
            let g_e1 = e2.cross(g_c);
            let g_e2 = g_c.cross(e1);
            for (i, d) in [(a, -(g_e1 + g_e2)), (b, g_e1), (c, g_e2)] {
                for k in 0..3 {
                    gp[3 * i + k] += T::from_f64(d[k]);
                }
            }
        }
        Ok(())
    }
}

/// Unit area-weighted vertex normals of `positions` [V, 3] over `triangles`, on the tape.
pub fn vertex_normals(triangles: Arc<[[u32; 3]]>, positions: &Tensor) -> Result<Tensor> {
    apply(VertexNormals { triangles }, &[positions])
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Mesh;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;
    use glam::Vec3;

    /// A bumpy tetrahedron-like fan: five vertices, four faces.
    fn fan() -> (Vec<f64>, Arc<[[u32; 3]]>) {
        let p = vec![0.0, 0.0, 0.3, 1.0, 0.1, 0.0, 0.2, 1.0, -0.1, -0.9, 0.3, 0.1, 0.1, -1.0, 0.2];
        (p, vec![[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 1]].into())
    }

    #[test]
    fn forward_is_the_meshs_rule() -> anyhow::Result<()> {
        let (p, tris) = fan();
        let t = Tensor::from_vec(p.clone(), (5, 3), &Device::Cpu)?;
        let got = vertex_normals(tris.clone(), &t)?.flatten_all()?.to_vec1::<f64>()?;
        let pos: Vec<Vec3> = p.chunks(3).map(|c| Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32)).collect();
        let want = Mesh::area_weighted_normals(&pos, &tris);
        for (v, w) in want.iter().enumerate() {
            for a in 0..3 {
                assert!((got[3 * v + a] - w[a] as f64).abs() < 1e-6, "vertex {v}: {got:?} vs {want:?}");
            }
        }
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let (p, tris) = fan();
        let t = Tensor::from_vec(p, (5, 3), &Device::Cpu)?;
        let report = check_gradient(|x| vertex_normals(tris.clone(), &x[0]), &[t], 1e-6, 1e-5)?;
        println!("{report}");
        Ok(())
    }

    #[test]
    fn slivers_and_zero_area_faces_keep_gradients_finite() -> anyhow::Result<()> {
        // Face [1, 3, 2] is a sliver (vertex 3 sits 1e-6 off the edge 1–2) between two normal faces.
        let p = vec![0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.5 + 1e-6, 0.5 + 1e-6, 0.0, 1.2, 1.1, 0.4];
        let t = Tensor::from_vec(p.clone(), (5, 3), &Device::Cpu)?;
        let tris: Arc<[[u32; 3]]> = vec![[0, 1, 2], [1, 3, 2], [1, 4, 3]].into();
        check_gradient(|x| vertex_normals(tris.clone(), &x[0]), &[t], 1e-8, 1e-4)?;
        // A zero-area face alone at a vertex: +z, and zero (finite) gradients.
        let mut q = p;
        q[9..12].copy_from_slice(&[0.5, 0.5, 0.0]);
        let v = candle_core::Var::from_tensor(&Tensor::from_vec(q, (5, 3), &Device::Cpu)?)?;
        let only: Arc<[[u32; 3]]> = vec![[1, 3, 2]].into();
        let n = vertex_normals(only, v.as_tensor())?;
        assert_eq!(n.get(3)?.to_vec1::<f64>()?, vec![0.0, 0.0, 1.0]);
        let g = n.sum_all()?.backward()?;
        let gv = g.get(v.as_tensor()).expect("gradient").flatten_all()?.to_vec1::<f64>()?;
        assert!(gv.iter().all(|x| x.is_finite()), "{gv:?}");
        Ok(())
    }
}
