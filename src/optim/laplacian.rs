//! Uniform ("umbrella") Laplacian over mesh edges, for the regulariser on vertex offsets:
//! (L x)_i = (1/|N(i)|) Σ_{j∈N(i)} x_j − x_i, and the loss mean_i,k ((L x)_ik)².
//! Applied to offsets from the initial mesh (NVDiffRec's "relative" mode) it keeps the optimised
//! surface as smooth as the start. No training run applies it today: the material and light fit
//! keeps the vertices fixed, and the geometry pass smooths through Large Steps instead
//! (docs/model.md, *Loss*). N(i) are the vertices sharing an edge with i (each edge once);
//! on a closed manifold this equals NVDiffRecMC's per-triangle accumulation. Vertices duplicated
//! along UV seams are separate vertices here, as in the mesh.
//!
//! L is linear, so its adjoint is Lᵀ: (Lᵀ g)_j = Σ_{i∈N(j)} g_i/|N(i)| − g_j; because N is
//! symmetric both directions are gathers over the same neighbour lists (no scatter, no races).

use std::sync::Arc;

use anyhow::bail;
use candle_core::{Result, Tensor};
use rayon::prelude::*;

use super::tape::{apply, Kernel, Real};

/// Neighbour lists in compressed rows.
#[derive(Clone, Debug)]
pub struct UniformLaplacian {
    offsets: Arc<Vec<usize>>,
    neighbours: Arc<Vec<u32>>,
}

impl UniformLaplacian {
    /// From a triangle list over `vertex_count` vertices; an index out of range is an error.
    pub fn new(vertex_count: usize, triangles: &[[u32; 3]]) -> anyhow::Result<Self> {
        let mut edges: Vec<(u32, u32)> = Vec::with_capacity(triangles.len() * 6);
        for (t, tri) in triangles.iter().enumerate() {
            if let Some(bad) = tri.iter().find(|&&v| v as usize >= vertex_count) {
                bail!("Laplacian: triangle {t} refers to vertex {bad}, but the mesh has {vertex_count} vertices");
            }
            for k in 0..3 {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                if a != b {
                    edges.push((a, b));
                    edges.push((b, a));
                }
            }
        }
        edges.par_sort_unstable();
        edges.dedup();
        let mut offsets = vec![0usize; vertex_count + 1];
        for &(a, _) in &edges {
            offsets[a as usize + 1] += 1;
        }
        for i in 0..vertex_count {
            offsets[i + 1] += offsets[i];
        }
        let neighbours = edges.into_iter().map(|(_, b)| b).collect();
        Ok(UniformLaplacian { offsets: Arc::new(offsets), neighbours: Arc::new(neighbours) })
    }

    pub fn vertex_count(&self) -> usize {
        self.offsets.len() - 1
    }

    /// Every edge once, as (a, b) with a < b.
    pub fn edges(&self) -> Vec<[u32; 2]> {
        (0..self.vertex_count())
            .flat_map(|a| self.neighbours[self.offsets[a]..self.offsets[a + 1]].iter().filter(move |&&b| b as usize > a).map(move |&b| [a as u32, b]))
            .collect()
    }

    #[inline]
    fn neighbours_of(&self, i: usize) -> &[u32] {
        &self.neighbours[self.offsets[i]..self.offsets[i + 1]]
    }

    /// L x for x: [V, K] (usually K = 3), on the tape.
    pub fn apply(&self, x: &Tensor) -> Result<Tensor> {
        apply(self.clone(), &[x])
    }

    /// mean((L x)²): the regulariser on vertex offsets x [V, 3].
    pub fn regularizer(&self, offsets: &Tensor) -> Result<Tensor> {
        self.apply(offsets)?.sqr()?.mean_all()
    }
}

impl Kernel for UniformLaplacian {
    fn name(&self) -> &'static str {
        "uniform_laplacian"
    }

    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[v, k]] if *v == self.vertex_count() && *k > 0 => Ok(vec![*v, *k]),
            _ => Err(candle_core::Error::Msg(format!(
                "Laplacian: expected [{}, K] vertex data, got {shapes:?}",
                self.vertex_count()
            ))),
        }
    }

    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        let (x, k) = (x[0], shapes[0][1]);
        out.par_chunks_mut(k).enumerate().for_each(|(i, o)| {
            let nb = self.neighbours_of(i);
            if nb.is_empty() {
                return;
            }
            let inv = T::from_f64(1.0 / nb.len() as f64);
            for &j in nb {
                for c in 0..k {
                    o[c] += x[j as usize * k + c] * inv;
                }
            }
            for c in 0..k {
                o[c] -= x[i * k + c];
            }
        });
        Ok(())
    }

    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(gx) = grads[0].as_deref_mut() else { return Ok(()) };
        let k = shapes[0][1];
        gx.par_chunks_mut(k).enumerate().for_each(|(j, o)| {
            let nb = self.neighbours_of(j);
            if nb.is_empty() {
                return; // an isolated vertex has L row 0 and appears in no other row
            }
            for &i in nb {
                let inv = T::from_f64(1.0 / self.neighbours_of(i as usize).len() as f64);
                for c in 0..k {
                    o[c] += g[i as usize * k + c] * inv;
                }
            }
            for c in 0..k {
                o[c] -= g[j * k + c];
            }
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    /// A closed octahedron: every vertex has 4 neighbours.
    fn octahedron() -> (usize, Vec<[u32; 3]>) {
        let t = vec![[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]];
        (6, t)
    }

    #[test]
    fn translations_are_free_and_a_bump_is_penalised() -> anyhow::Result<()> {
        let (n, t) = octahedron();
        let lap = UniformLaplacian::new(n, &t)?;
        let shift = Tensor::new(&[[0.3f64, -1.0, 2.0]], &Device::Cpu)?.repeat((n, 1))?;
        assert!(lap.regularizer(&shift)?.to_scalar::<f64>()?.abs() < 1e-12);
        // Move vertex 4 by 1 in z: L_4 = -1 (z), its 4 neighbours get +1/4.
        let mut bump = vec![0.0f64; n * 3];
        bump[4 * 3 + 2] = 1.0;
        let x = Tensor::from_vec(bump, (n, 3), &Device::Cpu)?;
        let want = (1.0 + 4.0 * 0.0625) / (n as f64 * 3.0);
        assert!((lap.regularizer(&x)?.to_scalar::<f64>()? - want).abs() < 1e-12);
        Ok(())
    }

    #[test]
    fn out_of_range_index_is_an_error() {
        let err = UniformLaplacian::new(3, &[[0, 1, 3]]).unwrap_err().to_string();
        assert!(err.contains("vertex 3"), "{err}");
    }

    #[test]
    fn gradient_matches_finite_differences_with_an_isolated_vertex() -> anyhow::Result<()> {
        // An open fan (boundary vertices have fewer neighbours) plus one unused vertex.
        let tris = vec![[0, 1, 2], [0, 2, 3], [0, 3, 4], [4, 3, 5]];
        let lap = UniformLaplacian::new(7, &tris)?;
        let x = Tensor::rand(-1f64, 1.0, (7, 3), &Device::Cpu)?;
        check_gradient(|a| lap.regularizer(&a[0]), &[x], 1e-6, 1e-2)?;
        Ok(())
    }
}
