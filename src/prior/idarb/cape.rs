//! CaPE (camera-as-relative-positional-encoding), the 4-DoF rotary pose encoding IDArb applies to
//! the query and key of its cross-view attention.
//!
//! Channel `c` of a `C`-channel projection is rotated by the angle `pose[view][c / (C/P)]` (each of
//! the `P` pose values covers a contiguous block of `C/P` channels), pairwise on **adjacent**
//! channels: (x₂ᵢ, x₂ᵢ₊₁) ↦ (x₂ᵢ cos θ − x₂ᵢ₊₁ sin θ, x₂ᵢ₊₁ cos θ + x₂ᵢ sin θ). Because each pair is a
//! plane rotation, q'·k' depends only on the pose difference of the two views.
use candle_core::{bail, Result, Tensor, D};

/// Rotate q or k of the cross-view attention.
/// `x`: [B·num_domains, N·L, C] with rows ordered (object, domain) and tokens (view, pixel);
/// `pose`: [B, N, P] angles in radians.
pub fn apply_cape(x: &Tensor, pose: &Tensor, num_domains: usize) -> Result<Tensor> {
    let (bd, nl, c) = x.dims3()?;
    let (b, n, p) = pose.dims3()?;
    if bd != b * num_domains || nl % n != 0 || c % (2 * p) != 0 {
        bail!("CaPE: x {:?} does not match pose {:?} with {num_domains} domains", x.dims(), pose.dims());
    }
    let l = nl / n;
    let pose = pose.to_dtype(x.dtype())?;
    // angle per channel: [B, N, P] → [B, N, P, C/P] → [B, 1, N, 1, C]
    let angles = pose.unsqueeze(3)?.broadcast_as((b, n, p, c / p))?.reshape((b, 1, n, 1, c))?;
    let (cos, sin) = (angles.cos()?, angles.sin()?);
    let x5 = x.reshape((b, num_domains, n, l, c))?;
    let pairs = x5.reshape((b, num_domains, n, l, c / 2, 2))?;
    let even = pairs.narrow(D::Minus1, 0, 1)?;
    let odd = pairs.narrow(D::Minus1, 1, 1)?;
    let rotated = Tensor::cat(&[odd.neg()?, even], D::Minus1)?.reshape((b, num_domains, n, l, c))?;
    let out = (x5.broadcast_mul(&cos)? + rotated.broadcast_mul(&sin)?)?;
    out.reshape((bd, nl, c))
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
        let q = Tensor::randn(0f32, 1.0, (1, 2 * l, c), &dev)?;
        let k = Tensor::randn(0f32, 1.0, (1, 2 * l, c), &dev)?;
        let dots = |p: [[f32; 4]; 2]| -> Vec<Vec<f32>> {
            let pose = Tensor::new(&[p], &dev).expect("test setup");
            let qr = apply_cape(&q, &pose, 1).expect("test setup");
            let kr = apply_cape(&k, &pose, 1).expect("test setup");
            // head-split as the attention does, then all q·k dot products
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

    /// Domains share the view's pose: each domain row is rotated identically.
    #[test]
    fn domains_share_pose() -> Result<()> {
        let dev = Device::Cpu;
        let row = Tensor::randn(0f32, 1.0, (1, 4, 8), &dev)?;
        let x = Tensor::cat(&[&row, &row, &row], 0)?; // 3 domains, N=2 views × L=2
        let pose = Tensor::new(&[[[0.2f32, 0.4, 0.6, 0.8], [1.0, -1.0, 0.5, 0.0]]], &dev)?;
        let y = apply_cape(&x, &pose, 3)?;
        let d = (y.narrow(0, 0, 1)? - y.narrow(0, 2, 1)?)?.abs()?.flatten_all()?.max(0)?.to_scalar::<f32>()?;
        assert_eq!(d, 0.0);
        Ok(())
    }
}
