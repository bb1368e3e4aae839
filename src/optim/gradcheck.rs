//! Finite-difference gradient checker used by every differentiable operator's tests.
//!
//! The operator's output y is reduced to a scalar L = Σ rₖ·yₖ with fixed pseudo-random weights
//! rₖ ∈ [0.5, 1.5] (so a wrong index or a swapped adjoint cannot hide behind a plain sum), in f64.
//! candle's backward gives g = ∂L/∂x; central differences give g_fd,i = (L(x+εeᵢ) − L(x−εeᵢ)) / 2ε.
//!
//! Metric, per input tensor: rel = max_i |g_i − g_fd,i| / max(max_i |g_fd,i|, 1e-6).
//! Normalising by the largest gradient of the tensor (not per element) keeps elements whose true
//! gradient is ~0 (clamped regions, far texels) from dominating through FD round-off, while any
//! error on the elements that matter shows at full size. The check passes when rel ≤ tol for every
//! input.

use std::fmt;

use anyhow::{bail, Context};
use candle_core::{DType, Tensor, Var};

use crate::rng::Sampler;

/// Absolute floor of the metric's denominator (see the module doc).
pub const GRAD_FLOOR: f64 = 1e-6;

/// How one input tensor fared.
#[derive(Clone, Debug)]
pub struct InputReport {
    pub input: usize,
    /// Elements compared (all, or an evenly spread subset for large tensors).
    pub checked: usize,
    pub max_abs_err: f64,
    pub max_abs_fd: f64,
    pub rel_err: f64,
    /// Flat index of the worst element, with its analytic and finite-difference gradients.
    pub worst_index: usize,
    pub analytic_at_worst: f64,
    pub fd_at_worst: f64,
}

#[derive(Clone, Debug)]
pub struct GradReport {
    pub inputs: Vec<InputReport>,
}

impl GradReport {
    /// The largest relative error over all inputs.
    pub fn rel_err(&self) -> f64 {
        self.inputs.iter().map(|r| r.rel_err).fold(0.0, f64::max)
    }
}

impl fmt::Display for GradReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for r in &self.inputs {
            writeln!(
                f,
                "input {}: rel err {:.3e} (max |g-g_fd| {:.3e}, max |g_fd| {:.3e}, {} elements; worst at {}: g {:.6e} vs fd {:.6e})",
                r.input, r.rel_err, r.max_abs_err, r.max_abs_fd, r.checked, r.worst_index, r.analytic_at_worst, r.fd_at_worst
            )?;
        }
        Ok(())
    }
}

/// Options beyond (eps, tol).
#[derive(Clone, Debug)]
pub struct GradCheckOptions {
    pub eps: f64,
    pub tol: f64,
    /// At most this many elements per input are perturbed (evenly spread, including first/last).
    pub max_elements: usize,
    pub seed: u64,
}

impl Default for GradCheckOptions {
    fn default() -> Self {
        GradCheckOptions { eps: 1e-6, tol: 1e-2, max_elements: 1500, seed: 17 }
    }
}

/// Compares candle's backward of `op` with central differences at `inputs` (converted to f64).
/// Returns the report when every input passes, an error carrying the report otherwise.
pub fn check_gradient<F>(op: F, inputs: &[Tensor], eps: f64, tol: f64) -> anyhow::Result<GradReport>
where
    F: Fn(&[Tensor]) -> candle_core::Result<Tensor>,
{
    check_gradient_with(op, inputs, &GradCheckOptions { eps, tol, ..Default::default() })
}

pub fn check_gradient_with<F>(op: F, inputs: &[Tensor], opts: &GradCheckOptions) -> anyhow::Result<GradReport>
where
    F: Fn(&[Tensor]) -> candle_core::Result<Tensor>,
{
    let base: Vec<Tensor> =
        inputs.iter().map(|t| t.to_dtype(DType::F64)?.contiguous()).collect::<candle_core::Result<_>>()?;
    let vars: Vec<Var> = base.iter().map(Var::from_tensor).collect::<candle_core::Result<_>>()?;
    let var_tensors: Vec<Tensor> = vars.iter().map(|v| v.as_tensor().clone()).collect();

    let y = op(&var_tensors).context("gradient check: forward failed")?;
    let mut rng = Sampler::from_seed(opts.seed);
    let weights: Vec<f64> = (0..y.elem_count()).map(|_| 0.5 + rng.next_f32() as f64).collect();
    let weights = Tensor::from_vec(weights, y.shape(), y.device())?;
    let scalar = |y: &Tensor| -> anyhow::Result<f64> {
        let l = (y.to_dtype(DType::F64)? * &weights)?.sum_all()?.to_scalar::<f64>()?;
        if !l.is_finite() {
            bail!("gradient check: the operator produced a non-finite value");
        }
        Ok(l)
    };
    let l0 = (y.to_dtype(DType::F64)? * &weights)?.sum_all()?;
    let grads = l0.backward()?;

    let mut reports = Vec::new();
    for (i, x) in base.iter().enumerate() {
        let n = x.elem_count();
        let analytic: Vec<f64> = match grads.get(vars[i].as_tensor()) {
            Some(g) => g.to_dtype(DType::F64)?.flatten_all()?.to_vec1::<f64>()?,
            None => vec![0.0; n],
        };
        let flat = x.flatten_all()?.to_vec1::<f64>()?;
        let picks: Vec<usize> = if n <= opts.max_elements {
            (0..n).collect()
        } else {
            let m = opts.max_elements.max(2);
            let mut p: Vec<usize> = (0..m).map(|k| k * (n - 1) / (m - 1)).collect();
            p.dedup();
            p
        };
        let mut rep = InputReport {
            input: i,
            checked: picks.len(),
            max_abs_err: 0.0,
            max_abs_fd: 0.0,
            rel_err: 0.0,
            worst_index: 0,
            analytic_at_worst: 0.0,
            fd_at_worst: 0.0,
        };
        for &k in &picks {
            let eval = |delta: f64| -> anyhow::Result<f64> {
                let mut v = flat.clone();
                v[k] += delta;
                let xt = Tensor::from_vec(v, x.shape(), x.device())?;
                let args: Vec<Tensor> =
                    base.iter().enumerate().map(|(j, b)| if j == i { xt.clone() } else { b.clone() }).collect();
                scalar(&op(&args)?)
            };
            let fd = (eval(opts.eps)? - eval(-opts.eps)?) / (2.0 * opts.eps);
            if !analytic[k].is_finite() {
                bail!("gradient check: input {i} element {k} has a non-finite analytic gradient {}", analytic[k]);
            }
            let err = (analytic[k] - fd).abs();
            rep.max_abs_fd = rep.max_abs_fd.max(fd.abs());
            if err > rep.max_abs_err || k == picks[0] {
                rep.max_abs_err = rep.max_abs_err.max(err);
                rep.worst_index = k;
                rep.analytic_at_worst = analytic[k];
                rep.fd_at_worst = fd;
            }
        }
        rep.rel_err = rep.max_abs_err / rep.max_abs_fd.max(GRAD_FLOOR);
        reports.push(rep);
    }
    let report = GradReport { inputs: reports };
    if report.rel_err() > opts.tol {
        bail!("gradient check failed (tol {:.1e}):\n{report}", opts.tol);
    }
    Ok(report)
}

/// Checks a fused operator against the composition of candle operators it replaces: `composed` and
/// `fused` are scalar losses of the same `vars` (f64), and must agree in value and in every
/// gradient element within `tol` relative to max(|composed|, 1). Where finite differences test an
/// adjoint against the function, this tests it against candle's own autodiff at the very points
/// (kinks, ties) where finite differences are least telling.
pub fn check_same_as_composition(composed: &Tensor, fused: &Tensor, vars: &[&Var], tol: f64) -> anyhow::Result<()> {
    let close = |c: f64, f: f64| (c - f).abs() <= tol * c.abs().max(1.0);
    let (c, f) = (composed.to_scalar::<f64>()?, fused.to_scalar::<f64>()?);
    if !close(c, f) {
        bail!("fused operator's value {f} differs from the composition's {c}");
    }
    let (gc, gf) = (composed.backward()?, fused.backward()?);
    for (v, var) in vars.iter().enumerate() {
        let values = |g: &candle_core::backprop::GradStore| -> anyhow::Result<Vec<f64>> {
            Ok(g.get(var.as_tensor()).with_context(|| format!("no gradient for input {v}"))?.flatten_all()?.to_vec1::<f64>()?)
        };
        for (i, (c, f)) in values(&gc)?.into_iter().zip(values(&gf)?).enumerate() {
            if !close(c, f) {
                bail!("input {v} element {i}: composition's gradient {c}, fused operator's {f}");
            }
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::Device;

    #[test]
    fn a_fused_operator_with_the_same_value_but_another_gradient_is_caught() -> anyhow::Result<()> {
        // At x = 1, x² and x agree in value (1) but not in slope (2 against 1).
        let x = Var::from_tensor(&Tensor::new(&[1.0f64], &Device::Cpu)?)?;
        let squared = x.as_tensor().sqr()?.sum_all()?;
        assert!(check_same_as_composition(&squared, &x.as_tensor().sqr()?.sum_all()?, &[&x], 1e-12).is_ok());
        let err = check_same_as_composition(&squared, &x.as_tensor().sum_all()?, &[&x], 1e-12).expect_err("another slope");
        assert!(err.to_string().contains("element 0"), "{err}");
        Ok(())
    }

    #[test]
    fn accepts_a_correct_gradient_and_rejects_a_wrong_one() -> anyhow::Result<()> {
        let x = Tensor::new(&[0.3f64, -1.2, 2.0], &Device::Cpu)?;
        // exp has an exact candle backward.
        let rep = check_gradient(|a| a[0].exp(), std::slice::from_ref(&x), 1e-6, 1e-6)?;
        assert!(rep.rel_err() < 1e-6, "{rep}");
        // A deliberately wrong adjoint: forward x², backward detached (gradient 0) on half the path.
        let wrong = check_gradient(|a| a[0].sqr()? + a[0].detach().sqr()?, &[x], 1e-6, 1e-2);
        assert!(wrong.is_err());
        Ok(())
    }
}
