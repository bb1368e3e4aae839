//! The Large Steps parameterisation of vertex positions (Nicolet, Jacobson and Jakob 2021) and its
//! "uniform Adam", which the geometry pass uses to move a mesh without tangling it.
//!
//! Positions x (V × 3) are optimised through u = (I + λL)·x, with L the combinatorial (uniform)
//! Laplacian of the mesh (L_ii = valence, L_ij = −1 for neighbours). A gradient step on u moves x by
//! (I + λL)⁻¹ of it: the smooth, low-frequency modes of the surface move almost as far as the step,
//! the high-frequency ones (the noise that tangles triangles) are damped by up to 1 + λ·2·valence.
//! The chain rule is ∂L/∂u = (I + λL)⁻¹ ∂L/∂x (the matrix is symmetric), one more solve. The matrix
//! is factored once per connectivity with faer's sparse Cholesky (AMD ordering); each solve is then
//! two sparse triangular sweeps, run sequentially (`FACTOR_PARALLELISM`).
//!
//! Uniform Adam: Adam's second moment is replaced by its maximum over all entries, so every vertex
//! takes the same step size. Per-vertex normalisation (plain Adam) would rescale the frequencies
//! the parameterisation has just filtered and bring the noise back.

use anyhow::{anyhow, Result};
use faer::dyn_stack::{MemBuffer, MemStack};
use faer::sparse::linalg::cholesky::{factorize_symbolic_cholesky, LltRef, SymbolicCholesky};
use faer::sparse::{SparseColMat, Triplet};
use faer::{Conj, Mat, Par, Side};

/// Smoothing weight λ of (I + λL). With the uniform Laplacian a step spreads over about √λ
/// vertex rings; 19 is the Large Steps paper's own default for meshes of a few tens of
/// thousands of vertices, and does not depend on the object's size (L has no length unit).
pub const DEFAULT_LAMBDA: f64 = 19.0;

/// faer's parallelism for the factorisation and the solves: sequential. Measured on a
/// 40 962-vertex icosphere (λ = 2, Intel Xeon 2 cores, 2026-12-03): one 3-column solve takes
/// 18 ms sequentially against 99 ms on faer's default (rayon) path, whose per-supernode tasks
/// cost more than the sweeps they split; the factorisation 113 ms against 148 ms. The geometry
/// pass solves twice per step, so this was most of its position update.
const FACTOR_PARALLELISM: Par = Par::Seq;

pub struct LargeSteps {
    n: usize,
    lambda: f64,
    /// Neighbours of each vertex (sorted, unique): L's off-diagonal pattern.
    neighbours: Vec<Vec<u32>>,
    /// The Cholesky factor of I + λL: its structure (with the fill-reducing permutation) and values.
    symbolic: SymbolicCholesky<usize>,
    values: Vec<f64>,
}

impl LargeSteps {
    /// Factor (I + λL) for a mesh of `vertex_count` vertices and these triangles.
    pub fn new(vertex_count: usize, triangles: &[[u32; 3]], lambda: f64) -> Result<LargeSteps> {
        let mut neighbours = vec![Vec::new(); vertex_count];
        for t in triangles {
            for e in 0..3 {
                let (a, b) = (t[e], t[(e + 1) % 3]);
                if a as usize >= vertex_count || b as usize >= vertex_count {
                    return Err(anyhow!("Large Steps: triangle {t:?} indexes past {vertex_count} vertices"));
                }
                neighbours[a as usize].push(b);
                neighbours[b as usize].push(a);
            }
        }
        for n in &mut neighbours {
            n.sort_unstable();
            n.dedup();
        }
        let mut entries = Vec::with_capacity(vertex_count * 7);
        for (i, n) in neighbours.iter().enumerate() {
            entries.push(Triplet::new(i, i, 1.0 + lambda * n.len() as f64));
            // Lower triangle only: the factorisation reads one side.
            entries.extend(n.iter().filter(|&&j| (j as usize) > i).map(|&j| Triplet::new(j as usize, i, -lambda)));
        }
        let a = SparseColMat::<usize, f64>::try_new_from_triplets(vertex_count, vertex_count, &entries)
            .map_err(|e| anyhow!("Large Steps: building I + λL: {e:?}"))?;
        let symbolic = factorize_symbolic_cholesky(a.symbolic(), Side::Lower, Default::default(), Default::default())
            .map_err(|e| anyhow!("Large Steps: ordering I + λL: {e:?}"))?;
        let mut values = vec![0.0; symbolic.len_val()];
        let scratch = symbolic.factorize_numeric_llt_scratch::<f64>(FACTOR_PARALLELISM, Default::default());
        let mut buffer = MemBuffer::try_new(scratch).map_err(|e| anyhow!("Large Steps: factor workspace: {e:?}"))?;
        symbolic
            .factorize_numeric_llt(
                &mut values,
                a.as_ref(),
                Side::Lower,
                Default::default(),
                FACTOR_PARALLELISM,
                MemStack::new(&mut buffer),
                Default::default(),
            )
            .map_err(|e| anyhow!("Large Steps: factoring I + λL: {e:?}"))?;
        Ok(LargeSteps { n: vertex_count, lambda, neighbours, symbolic, values })
    }

    pub fn vertex_count(&self) -> usize {
        self.n
    }

    /// u = (I + λL)·x, row-major V × 3.
    pub fn to_u(&self, x: &[[f64; 3]]) -> Vec<[f64; 3]> {
        x.iter()
            .zip(&self.neighbours)
            .map(|(xi, nb)| {
                let k = nb.len() as f64;
                std::array::from_fn(|a| {
                    let sum: f64 = nb.iter().map(|&j| x[j as usize][a]).sum();
                    xi[a] + self.lambda * (k * xi[a] - sum)
                })
            })
            .collect()
    }

    /// (I + λL)⁻¹·b: positions from u, and ∂L/∂u from ∂L/∂x.
    pub fn solve(&self, b: &[[f64; 3]]) -> Vec<[f64; 3]> {
        let mut rhs = Mat::<f64>::from_fn(self.n, 3, |i, a| b[i][a]);
        let mut buffer = MemBuffer::new(self.symbolic.solve_in_place_scratch::<f64>(3, FACTOR_PARALLELISM));
        LltRef::new(&self.symbolic, &self.values).solve_in_place_with_conj(Conj::No, rhs.as_mut(), FACTOR_PARALLELISM, MemStack::new(&mut buffer));
        (0..self.n).map(|i| std::array::from_fn(|a| rhs[(i, a)])).collect()
    }
}

/// Adam with one second moment for all entries (its maximum), as Large Steps uses on u.
pub struct UniformAdam {
    pub lr: f64,
    beta1: f64,
    beta2: f64,
    eps: f64,
    m: Vec<[f64; 3]>,
    v: Vec<[f64; 3]>,
    t: i32,
}

impl UniformAdam {
    /// Adam's usual betas (0.9, 0.999) and ε.
    pub fn new(n: usize, lr: f64) -> Self {
        UniformAdam { lr, beta1: 0.9, beta2: 0.999, eps: 1e-8, m: vec![[0.0; 3]; n], v: vec![[0.0; 3]; n], t: 0 }
    }

    /// First and second moments and the step count (for checkpoints).
    pub fn state(&self) -> (&[[f64; 3]], &[[f64; 3]], i32) {
        (&self.m, &self.v, self.t)
    }

    /// Restores [`UniformAdam::state`].
    pub fn restore(&mut self, m: Vec<[f64; 3]>, v: Vec<[f64; 3]>, t: i32) {
        (self.m, self.v, self.t) = (m, v, t);
    }

    /// The update to add to u for gradient `g` (on u) with learning-rate factor `scale`.
    pub fn step(&mut self, g: &[[f64; 3]], scale: f64) -> Vec<[f64; 3]> {
        self.t += 1;
        let (b1, b2) = (self.beta1, self.beta2);
        let mut vmax: f64 = 0.0;
        for ((m, v), g) in self.m.iter_mut().zip(&mut self.v).zip(g) {
            for a in 0..3 {
                m[a] = b1 * m[a] + (1.0 - b1) * g[a];
                v[a] = b2 * v[a] + (1.0 - b2) * g[a] * g[a];
                vmax = vmax.max(v[a]);
            }
        }
        let m_hat = 1.0 - b1.powi(self.t);
        let v_hat = 1.0 - b2.powi(self.t);
        let denom = (vmax / v_hat).sqrt() + self.eps;
        let lr = self.lr * scale;
        self.m.iter().map(|m| std::array::from_fn(|a| -lr * (m[a] / m_hat) / denom)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn strip() -> (usize, Vec<[u32; 3]>) {
        // A 4×3 vertex grid, two triangles per cell.
        let (w, h) = (4u32, 3u32);
        let mut t = Vec::new();
        for y in 0..h - 1 {
            for x in 0..w - 1 {
                let i = y * w + x;
                t.push([i, i + 1, i + w + 1]);
                t.push([i, i + w + 1, i + w]);
            }
        }
        ((w * h) as usize, t)
    }

    #[test]
    fn solve_inverts_the_product() -> Result<()> {
        let (n, tris) = strip();
        let ls = LargeSteps::new(n, &tris, 7.0)?;
        let x: Vec<[f64; 3]> = (0..n).map(|i| [i as f64 * 0.3, (i * i % 5) as f64, -(i as f64).sin()]).collect();
        let back = ls.solve(&ls.to_u(&x));
        for (a, b) in x.iter().zip(&back) {
            for k in 0..3 {
                assert!((a[k] - b[k]).abs() < 1e-10, "{a:?} vs {b:?}");
            }
        }
        Ok(())
    }

    #[test]
    fn a_translation_passes_unchanged_and_noise_is_damped() -> Result<()> {
        let (n, tris) = strip();
        let ls = LargeSteps::new(n, &tris, DEFAULT_LAMBDA)?;
        // L·1 = 0, so a uniform step on u is the same step on x.
        let ones = ls.solve(&vec![[1.0, 2.0, 3.0]; n]);
        assert!(ones.iter().all(|v| (v[0] - 1.0).abs() < 1e-9 && (v[1] - 2.0).abs() < 1e-9 && (v[2] - 3.0).abs() < 1e-9));
        // A checkerboard (the highest frequency) shrinks by a large factor.
        let noise: Vec<[f64; 3]> = (0..n).map(|i| [if (i % 4 + i / 4) % 2 == 0 { 1.0 } else { -1.0 }, 0.0, 0.0]).collect();
        let damped = ls.solve(&noise);
        let max = damped.iter().map(|v| v[0].abs()).fold(0.0, f64::max);
        assert!(max < 0.1, "checkerboard kept {max}");
        Ok(())
    }

    #[test]
    fn uniform_adam_takes_one_step_size() {
        let mut adam = UniformAdam::new(2, 0.1);
        let d = adam.step(&[[1.0, 0.0, 0.0], [100.0, 0.0, 0.0]], 1.0);
        // Second moment shared: the small gradient moves 1/100 of the large one, which moves lr.
        assert!((d[1][0] + 0.1).abs() < 1e-6 && (d[0][0] + 0.001).abs() < 1e-6, "{d:?}");
    }
}
