//! CaPE (camera-as-relative-positional-encoding), the 4-DoF rotary pose encoding IDArb applies to
//! the query and key of its cross-view attention.
//!
//! Channel `c` of a `C`-channel projection is rotated by the angle `pose[view][c / (C/P)]` (each of
//! the `P` pose values covers a contiguous block of `C/P` channels), pairwise on **adjacent**
//! channels: (x₂ᵢ, x₂ᵢ₊₁) ↦ (x₂ᵢ cos θ − x₂ᵢ₊₁ sin θ, x₂ᵢ₊₁ cos θ + x₂ᵢ sin θ). Because each pair is a
//! plane rotation, q'·k' depends only on the pose difference of the two views.
use crate::optim::tape::contiguous_slice;
use candle_core::{bail, CpuStorage, CustomOp2, Layout, Result, Shape, Tensor};
use rayon::prelude::*;

/// Rotate q or k of the cross-view attention, in one parallel pass.
/// `x`: [B·N·num_domains, L, C] with rows ordered (object, view, domain) (the UNet's own order);
/// `pose`: [B, N, P] angles in radians.
pub fn apply_cape(x: &Tensor, pose: &Tensor, num_domains: usize) -> Result<Tensor> {
    x.contiguous()?.apply_op2_no_bwd(&pose.to_dtype(candle_core::DType::F32)?.contiguous()?, &Cape { num_domains })
}

struct Cape {
    num_domains: usize,
}

impl CustomOp2 for Cape {
    fn name(&self) -> &'static str {
        "idarb-cape"
    }

    fn cpu_fwd(&self, xs: &CpuStorage, xl: &Layout, ps: &CpuStorage, pl: &Layout) -> Result<(CpuStorage, Shape)> {
        let (x, pose) = (contiguous_slice::<f32>(self.name(), xs, xl)?, contiguous_slice::<f32>(self.name(), ps, pl)?);
        let (rows, l, c) = xl.shape().dims3()?;
        let (b, n, p) = pl.shape().dims3()?;
        if rows != b * n * self.num_domains || p == 0 || c % (2 * p) != 0 {
            bail!("CaPE: x {:?} does not match pose {:?} with {} domains", xl.shape(), pl.shape(), self.num_domains);
        }
        let (cos, sin): (Vec<f32>, Vec<f32>) = pose.iter().map(|a| (a.cos(), a.sin())).unzip();
        let block = c / p; // channels per pose value, even, so a pair never straddles two
        let mut out = vec![0f32; x.len()];
        if l > 0 && c > 0 {
            out.par_chunks_mut(l * c).zip(x.par_chunks(l * c)).enumerate().for_each(|(r, (out, x))| {
                let view = r / self.num_domains; // object · N + view, the pose row
                let (cos, sin) = (&cos[view * p..(view + 1) * p], &sin[view * p..(view + 1) * p]);
                for (out, x) in out.chunks_exact_mut(c).zip(x.chunks_exact(c)) {
                    for (i, (o, x)) in out.chunks_exact_mut(2).zip(x.chunks_exact(2)).enumerate() {
                        let j = 2 * i / block;
                        o[0] = x[0] * cos[j] - x[1] * sin[j];
                        o[1] = x[1] * cos[j] + x[0] * sin[j];
                    }
                }
            });
        }
        Ok((CpuStorage::F32(out), Shape::from_dims(&[rows, l, c])))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, DType};

    fn vec2(t: &Tensor) -> Vec<Vec<f32>> {
        t.squeeze(0).expect("test setup").to_dtype(DType::F32).expect("test setup").to_vec2().expect("test setup")
    }

    /// C = 8, P = 4: pose value j rotates exactly the pair (2j, 2j+1); worked by hand.
    #[test]
    fn hand_computed_rotation() -> Result<()> {
        let dev = Device::Cpu;
        let x = Tensor::new(&[[[1f32, 0., 0., 1., 2., 3., 1., 1.]]], &dev)?; // B·D=1, N·L=1, C=8
        let th = [0.3f32, 0.7, -1.1, 2.0];
        let pose = Tensor::new(&[[th]], &dev)?; // [1,1,4]
        let y = vec2(&apply_cape(&x, &pose, 1)?)[0].clone();
        let (c, s) = (|t: f32| t.cos(), |t: f32| t.sin());
        let expect = [
            c(th[0]), s(th[0]), // (1,0) → (cos, sin)
            -s(th[1]), c(th[1]), // (0,1) → (−sin, cos)
            2. * c(th[2]) - 3. * s(th[2]), 3. * c(th[2]) + 2. * s(th[2]),
            c(th[3]) - s(th[3]), c(th[3]) + s(th[3]),
        ];
        for (a, e) in y.iter().zip(expect) {
            assert!((a - e).abs() < 1e-6, "{y:?} vs {expect:?}");
        }
        Ok(())
    }

    /// Per-head q·k between two views depends only on the pose difference: shifting both poses by
    /// the same offset keeps every dot product; changing the difference does not.
    #[test]
    fn dot_product_depends_only_on_pose_difference() -> Result<()> {
        let dev = Device::Cpu;
        let (c, l, heads) = (16usize, 3usize, 2usize);
        // rows = the two views of one object (one domain), L tokens each
        let q = Tensor::randn(0f32, 1.0, (2, l, c), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (2, l, c), &dev)?;
        let dots = |p: [[f32; 4]; 2]| -> Vec<Vec<f32>> {
            let pose = Tensor::new(&[p], &dev).expect("test setup");
            let qr = apply_cape(&q, &pose, 1).expect("test setup").reshape((1, 2 * l, c)).expect("test setup");
            let kr = apply_cape(&k, &pose, 1).expect("test setup").reshape((1, 2 * l, c)).expect("test setup");
            // head-split as the attention does, then all q·k dot products across both views
            let qh = crate::prior::idarb::attention::heads_to_batch(&qr, heads).expect("test setup");
            let kh = crate::prior::idarb::attention::heads_to_batch(&kr, heads).expect("test setup");
            let d = qh.matmul(&kh.t().expect("test setup")).expect("test setup");
            d.flatten_to(1).expect("test setup").to_vec2().expect("test setup")
        };
        let base = dots([[0.1, -0.4, 1.2, 0.0], [0.9, 0.5, -0.3, 0.2]]);
        let shifted = dots([[0.1 + 0.7, -0.4 - 1.3, 1.2 + 0.25, 0.0 + 2.0], [0.9 + 0.7, 0.5 - 1.3, -0.3 + 0.25, 0.2 + 2.0]]);
        let changed = dots([[0.1, -0.4, 1.2, 0.0], [0.9 + 0.6, 0.5, -0.3, 0.2]]);
        let maxdiff = |a: &Vec<Vec<f32>>, b: &Vec<Vec<f32>>| {
            a.iter().flatten().zip(b.iter().flatten()).map(|(x, y)| (x - y).abs()).fold(0f32, f32::max)
        };
        assert!(maxdiff(&base, &shifted) < 1e-4, "shift changed q·k by {}", maxdiff(&base, &shifted));
        assert!(maxdiff(&base, &changed) > 1e-2, "pose difference had no effect");
        Ok(())
    }

    /// Domains share the view's pose: the three domain rows of a view are rotated identically,
    /// and the next view's rows by its own pose.
    #[test]
    fn domains_share_pose() -> Result<()> {
        let dev = Device::Cpu;
        let row = Tensor::randn(0f32, 1.0, (1, 2, 8), &dev)?;
        let x = Tensor::cat(&[&row; 6], 0)?; // rows (view, domain): N = 2 views × 3 domains, L = 2
        let pose = Tensor::new(&[[[0.2f32, 0.4, 0.6, 0.8], [1.0, -1.0, 0.5, 0.0]]], &dev)?;
        let y = apply_cape(&x, &pose, 3)?;
        let diff = |a: usize, b: usize| -> Result<f32> {
            (y.narrow(0, a, 1)? - y.narrow(0, b, 1)?)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()
        };
        assert_eq!(diff(0, 2)?, 0.0);
        assert_eq!(diff(3, 5)?, 0.0);
        assert!(diff(0, 3)? > 1e-3, "the two views were rotated alike");
        Ok(())
    }
}
