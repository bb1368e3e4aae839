//! The tape pattern: candle's autodiff (`Var`, `backward`) records the graph, and each render kernel
//! enters it as one custom operator whose forward and adjoint live side by side in a [`Kernel`].
//!
//! A kernel works on plain contiguous slices (f32 or f64, chosen by the input tensors' dtype), so
//! it can be a rayon loop; [`apply`] wraps it as a candle `CustomOp1/2/3`. The adjoint writes into
//! zeroed gradient buffers; [`scatter_add_banded`] gives scatter-style adjoints (texture lookups)
//! a race-free, deterministic way to accumulate in parallel.
//!
//! Conventions for renderer kernels:
//! - Fixed data (G-buffer, UVs, guides, seeds) lives in the kernel struct, not in tensors.
//! - Random numbers: keep the seed in the struct and draw per-pixel streams
//!   (`rng::Sampler::new(seed, pixel)`) in both passes, so the backward replays the forward's samples.
//! - State the backward needs and the forward computes (e.g. shadow-ray visibility) is computed in
//!   the kernel's constructor, or recomputed in the backward: `Kernel::forward` takes `&self`.
//! - Float work inside a kernel may be done in f64 whatever `T` is; checks run the whole op in f64.

use std::sync::Arc;

use candle_core::{
    CpuStorage, CustomOp1, CustomOp2, CustomOp3, DType, Layout, Result, Shape, Storage, Tensor,
    WithDType,
};
use rayon::prelude::*;

/// The float types kernels are written for (f32 for speed, f64 for gradient checks).
pub trait Real: WithDType + Default {
    fn sqrt(self) -> Self;
    fn exp(self) -> Self;
    fn ln(self) -> Self;
    fn powf(self, e: Self) -> Self;
    fn floor(self) -> Self;
    fn abs(self) -> Self;
    fn fmax(self, o: Self) -> Self;
    fn fmin(self, o: Self) -> Self;
    fn is_finite(self) -> bool;
}

macro_rules! impl_real {
    ($t:ty) => {
        impl Real for $t {
            #[inline]
            fn sqrt(self) -> Self {
                <$t>::sqrt(self)
            }
            #[inline]
            fn exp(self) -> Self {
                <$t>::exp(self)
            }
            #[inline]
            fn ln(self) -> Self {
                <$t>::ln(self)
            }
            #[inline]
            fn powf(self, e: Self) -> Self {
                <$t>::powf(self, e)
            }
            #[inline]
            fn floor(self) -> Self {
                <$t>::floor(self)
            }
            #[inline]
            fn abs(self) -> Self {
                <$t>::abs(self)
            }
            #[inline]
            fn fmax(self, o: Self) -> Self {
                <$t>::max(self, o)
            }
            #[inline]
            fn fmin(self, o: Self) -> Self {
                <$t>::min(self, o)
            }
            #[inline]
            fn is_finite(self) -> bool {
                <$t>::is_finite(self)
            }
        }
    };
}
impl_real!(f32);
impl_real!(f64);

/// A differentiable operator: forward and adjoint over contiguous slices, sharing their code path
/// (typically one helper that yields the stencil/weights, used by both).
///
/// `inputs[i]` is the i-th tensor's data in row-major order and `shapes[i]` its dims.
pub trait Kernel: Send + Sync + 'static {
    fn name(&self) -> &'static str;

    /// The output dims for these input dims (validate the inputs here: it runs first).
    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>>;

    /// Writes the result into `out` (zeroed, `output_shape` elements).
    fn forward<T: Real>(&self, inputs: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()>;

    /// Adds ∂L/∂inputs[i] = J_iᵀ · grad_out into `grads[i]` (zeroed) for every `Some` slot; a `None`
    /// slot is an input nothing upstream needs a gradient for, so its adjoint can be skipped.
    fn backward<T: Real>(
        &self,
        inputs: &[&[T]],
        shapes: &[&[usize]],
        grad_out: &[T],
        grads: &mut [Option<&mut [T]>],
    ) -> Result<()>;
}

/// Applies `kernel` to its input tensors (all f32 or all f64, on the CPU) and records it on the
/// tape. candle's custom ops take 1–3 tensors; with more, the inputs are flattened and
/// concatenated into one tensor (one copy; candle's `cat` backward splits the gradient again) and
/// the kernel still sees them separately; then every input's adjoint is computed.
pub fn apply<K: Kernel>(kernel: K, inputs: &[&Tensor]) -> Result<Tensor> {
    let c: Vec<Tensor> = inputs.iter().map(|t| t.contiguous()).collect::<Result<_>>()?;
    match c.as_slice() {
        [] => Err(candle_core::Error::Msg(format!("{}: no input tensors", kernel.name()))),
        [a] => a.apply_op1(KernelOp(Arc::new(kernel))),
        [a, b] => a.apply_op2(b, KernelOp(Arc::new(kernel))),
        [a, b, d] => a.apply_op3(b, d, KernelOp(Arc::new(kernel))),
        many => {
            let shapes: Vec<Vec<usize>> = many.iter().map(|t| t.dims().to_vec()).collect();
            let flat: Vec<Tensor> = many.iter().map(|t| t.flatten_all()).collect::<Result<_>>()?;
            let packed = Tensor::cat(&flat, 0)?;
            packed.apply_op1(KernelOp(Arc::new(Packed { inner: kernel, shapes })))
        }
    }
}

/// A kernel with more than three inputs, run on their concatenation.
struct Packed<K> {
    inner: K,
    shapes: Vec<Vec<usize>>,
}

impl<K: Kernel> Packed<K> {
    fn sizes(&self) -> impl Iterator<Item = usize> + '_ {
        self.shapes.iter().map(|s| s.iter().product())
    }
    fn shape_refs(&self) -> Vec<&[usize]> {
        self.shapes.iter().map(|s| s.as_slice()).collect()
    }
    fn split<'a, T>(&self, mut data: &'a [T]) -> Vec<&'a [T]> {
        self.sizes()
            .map(|n| {
                let (head, tail) = data.split_at(n);
                data = tail;
                head
            })
            .collect()
    }
}

impl<K: Kernel> Kernel for Packed<K> {
    fn name(&self) -> &'static str {
        self.inner.name()
    }
    fn output_shape(&self, _: &[&[usize]]) -> Result<Vec<usize>> {
        self.inner.output_shape(&self.shape_refs())
    }
    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        self.inner.forward(&self.split(x[0]), &self.shape_refs(), out)
    }
    fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let Some(mut all) = grads[0].take() else { return Ok(()) };
        let mut parts: Vec<Option<&mut [T]>> = Vec::with_capacity(self.shapes.len());
        for n in self.sizes() {
            let (head, tail) = std::mem::take(&mut all).split_at_mut(n);
            parts.push(Some(head));
            all = tail;
        }
        self.inner.backward(&self.split(x[0]), &self.shape_refs(), g, &mut parts)
    }
}

/// Runs only the forward of `kernel` (no tape entry), e.g. for evaluation renders.
pub fn apply_no_grad<K: Kernel>(kernel: K, inputs: &[&Tensor]) -> Result<Tensor> {
    let t: Vec<Tensor> = inputs.iter().map(|t| t.detach()).collect();
    let refs: Vec<&Tensor> = t.iter().collect();
    apply(kernel, &refs)
}

struct KernelOp<K>(Arc<K>);

/// The elements of a contiguous CPU tensor of element type `T`, in order: how every custom op
/// (the tape's kernels, Adam's update, the IDArb kernels) reads its inputs. A strided layout or
/// another dtype is an error naming the op `name`.
pub fn contiguous_slice<'a, T: WithDType>(name: &'static str, s: &'a CpuStorage, l: &Layout) -> Result<&'a [T]> {
    let data = T::cpu_storage_as_slice(s)?;
    match l.contiguous_offsets() {
        Some((a, b)) => Ok(&data[a..b]),
        None => Err(candle_core::Error::RequiresContiguous { op: name }),
    }
}

fn storage_slice<'a, T: WithDType>(name: &'static str, s: &'a Storage, l: &Layout) -> Result<&'a [T]> {
    match s {
        Storage::Cpu(c) => contiguous_slice::<T>(name, c, l),
        _ => Err(candle_core::Error::Msg(format!("{name}: CPU tensors only"))),
    }
}

fn forward_typed<T: Real, K: Kernel>(k: &K, args: &[(&CpuStorage, &Layout)]) -> Result<(CpuStorage, Shape)> {
    let slices: Vec<&[T]> =
        args.iter().map(|(s, l)| contiguous_slice::<T>(k.name(), s, l)).collect::<Result<_>>()?;
    let shapes: Vec<&[usize]> = args.iter().map(|(_, l)| l.dims()).collect();
    let out_dims = k.output_shape(&shapes)?;
    let mut out = vec![T::zero(); out_dims.iter().product()];
    k.forward(&slices, &shapes, &mut out)?;
    Ok((T::to_cpu_storage_owned(out), Shape::from(out_dims)))
}

fn forward_dispatch<K: Kernel>(k: &K, args: &[(&CpuStorage, &Layout)]) -> Result<(CpuStorage, Shape)> {
    match candle_core::backend::BackendStorage::dtype(args[0].0) {
        DType::F32 => forward_typed::<f32, K>(k, args),
        DType::F64 => forward_typed::<f64, K>(k, args),
        other => Err(candle_core::Error::UnsupportedDTypeForOp(other, k.name())),
    }
}

fn backward_typed<T: Real, K: Kernel>(k: &K, args: &[&Tensor], grad_out: &Tensor) -> Result<Vec<Option<Tensor>>> {
    let grad_out = grad_out.contiguous()?;
    let guards: Vec<_> = args.iter().map(|t| t.storage_and_layout()).collect();
    let (g_guard, g_layout) = grad_out.storage_and_layout();
    let slices: Vec<&[T]> =
        guards.iter().map(|(s, l)| storage_slice::<T>(k.name(), s, l)).collect::<Result<_>>()?;
    let grad_slice: &[T] = storage_slice::<T>(k.name(), &g_guard, g_layout)?;
    let shapes: Vec<&[usize]> = args.iter().map(|t| t.dims()).collect();
    let mut grads: Vec<Option<Vec<T>>> =
        args.iter().map(|t| t.track_op().then(|| vec![T::zero(); t.elem_count()])).collect();
    {
        let mut refs: Vec<Option<&mut [T]>> = grads.iter_mut().map(|g| g.as_deref_mut()).collect();
        k.backward(&slices, &shapes, grad_slice, &mut refs)?;
    }
    drop(guards);
    grads
        .into_iter()
        .zip(args)
        .map(|(g, a)| g.map(|g| Tensor::from_vec(g, a.shape(), a.device())).transpose())
        .collect()
}

fn backward_dispatch<K: Kernel>(k: &K, args: &[&Tensor], grad_out: &Tensor) -> Result<Vec<Option<Tensor>>> {
    match grad_out.dtype() {
        DType::F32 => backward_typed::<f32, K>(k, args, grad_out),
        DType::F64 => backward_typed::<f64, K>(k, args, grad_out),
        other => Err(candle_core::Error::UnsupportedDTypeForOp(other, k.name())),
    }
}

impl<K: Kernel> CustomOp1 for KernelOp<K> {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn cpu_fwd(&self, s: &CpuStorage, l: &Layout) -> Result<(CpuStorage, Shape)> {
        forward_dispatch(&*self.0, &[(s, l)])
    }
    fn bwd(&self, a: &Tensor, _res: &Tensor, g: &Tensor) -> Result<Option<Tensor>> {
        let mut v = backward_dispatch(&*self.0, &[a], g)?;
        Ok(v.remove(0))
    }
}

impl<K: Kernel> CustomOp2 for KernelOp<K> {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn cpu_fwd(&self, s1: &CpuStorage, l1: &Layout, s2: &CpuStorage, l2: &Layout) -> Result<(CpuStorage, Shape)> {
        forward_dispatch(&*self.0, &[(s1, l1), (s2, l2)])
    }
    fn bwd(&self, a: &Tensor, b: &Tensor, _res: &Tensor, g: &Tensor) -> Result<(Option<Tensor>, Option<Tensor>)> {
        let mut v = backward_dispatch(&*self.0, &[a, b], g)?.into_iter();
        Ok((v.next().flatten(), v.next().flatten()))
    }
}

impl<K: Kernel> CustomOp3 for KernelOp<K> {
    fn name(&self) -> &'static str {
        self.0.name()
    }
    fn cpu_fwd(
        &self,
        s1: &CpuStorage,
        l1: &Layout,
        s2: &CpuStorage,
        l2: &Layout,
        s3: &CpuStorage,
        l3: &Layout,
    ) -> Result<(CpuStorage, Shape)> {
        forward_dispatch(&*self.0, &[(s1, l1), (s2, l2), (s3, l3)])
    }
    fn bwd(
        &self,
        a: &Tensor,
        b: &Tensor,
        c: &Tensor,
        _res: &Tensor,
        g: &Tensor,
    ) -> Result<(Option<Tensor>, Option<Tensor>, Option<Tensor>)> {
        let mut v = backward_dispatch(&*self.0, &[a, b, c], g)?.into_iter();
        Ok((v.next().flatten(), v.next().flatten(), v.next().flatten()))
    }
}

/// One band of an output buffer that a scatter may write to; writes outside the band are dropped
/// (another band owns them).
pub struct BandSink<'a, T> {
    start: usize,
    data: &'a mut [T],
}

impl<T: Real> BandSink<'_, T> {
    #[inline]
    pub fn add(&mut self, index: usize, value: T) {
        if let Some(d) = index.checked_sub(self.start).and_then(|i| self.data.get_mut(i)) {
            *d += value;
        }
    }
}

/// Race-free parallel scatter-add: `out` is cut into one contiguous band per rayon thread; every
/// band visits all `n_items` and keeps only its own writes. No atomics, no per-thread copies of
/// `out`, and every element sums its contributions in item order, so the result is bit-identical
/// for any thread count. The price is that each band recomputes the (cheap) stencil of every item.
pub fn scatter_add_banded<T, F>(out: &mut [T], n_items: usize, scatter: F)
where
    T: Real,
    F: Fn(usize, &mut BandSink<T>) + Sync,
{
    if out.is_empty() {
        return;
    }
    let bands = rayon::current_num_threads().max(1);
    let band_len = out.len().div_ceil(bands);
    out.par_chunks_mut(band_len).enumerate().for_each(|(b, chunk)| {
        let mut sink = BandSink { start: b * band_len, data: chunk };
        for i in 0..n_items {
            scatter(i, &mut sink);
        }
    });
}

/// Parallel map with a scatter-add on the side, for items whose contributions are too costly to
/// recompute per band as [`scatter_add_banded`] does: `f(i, sum)` returns item `i`'s own result
/// and adds its contributions into `sum` (length `sum_len`). The items are cut into fixed chunks of
/// `items_per_chunk`, each summing into a zeroed copy of `sum`, and the copies are added in chunk
/// order. The chunking does not depend on the thread count, so neither does the rounding: the
/// result is bit-identical on any number of threads. Memory: one `sum_len` copy per chunk.
pub fn map_scatter_chunked<R, F>(n_items: usize, items_per_chunk: usize, sum_len: usize, f: F) -> (Vec<R>, Vec<f64>)
where
    R: Send,
    F: Fn(usize, &mut [f64]) -> R + Sync,
{
    let per_chunk = items_per_chunk.max(1);
    let partial: Vec<(Vec<R>, Vec<f64>)> = (0..n_items.div_ceil(per_chunk))
        .into_par_iter()
        .map(|c| {
            let mut sum = vec![0.0; sum_len];
            let results = (c * per_chunk..((c + 1) * per_chunk).min(n_items)).map(|i| f(i, &mut sum)).collect();
            (results, sum)
        })
        .collect();
    let mut results = Vec::with_capacity(n_items);
    let mut sum = vec![0.0; sum_len];
    for (r, s) in partial {
        results.extend(r);
        for (o, v) in sum.iter_mut().zip(&s) {
            *o += v;
        }
    }
    (results, sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use candle_core::{Device, Var};

    /// y = a ⊙ b + a²: exercises a two-input kernel, both adjoints.
    struct MulAddSquare;
    impl Kernel for MulAddSquare {
        fn name(&self) -> &'static str {
            "mul_add_square"
        }
        fn output_shape(&self, s: &[&[usize]]) -> Result<Vec<usize>> {
            if s[0] != s[1] {
                return Err(candle_core::Error::Msg("shape mismatch".into()));
            }
            Ok(s[0].to_vec())
        }
        fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
            out.par_iter_mut().enumerate().for_each(|(i, o)| *o = x[0][i] * x[1][i] + x[0][i] * x[0][i]);
            Ok(())
        }
        fn backward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
            let two = T::from_f64(2.0);
            if let Some(ga) = grads[0].as_deref_mut() {
                ga.par_iter_mut().enumerate().for_each(|(i, v)| *v += g[i] * (x[1][i] + two * x[0][i]));
            }
            if let Some(gb) = grads[1].as_deref_mut() {
                gb.par_iter_mut().enumerate().for_each(|(i, v)| *v += g[i] * x[0][i]);
            }
            Ok(())
        }
    }

    #[test]
    fn kernel_gradients_reach_vars_in_f32_and_f64() -> Result<()> {
        for dtype in [DType::F32, DType::F64] {
            let a = Var::from_tensor(&Tensor::new(&[1.0f64, -2.0, 0.5], &Device::Cpu)?.to_dtype(dtype)?)?;
            let b = Tensor::new(&[3.0f64, 4.0, -1.0], &Device::Cpu)?.to_dtype(dtype)?;
            let y = apply(MulAddSquare, &[a.as_tensor(), &b])?;
            let vals = y.to_dtype(DType::F64)?.to_vec1::<f64>()?;
            assert_eq!(vals, vec![4.0, -4.0, -0.25]);
            let grads = y.sum_all()?.backward()?;
            let ga = grads.get(a.as_tensor()).expect("grad of a").to_dtype(DType::F64)?.to_vec1::<f64>()?;
            assert_eq!(ga, vec![5.0, 0.0, 0.0]);
            // b is a constant: no gradient is computed or stored for it.
            assert!(grads.get(&b).is_none());
        }
        Ok(())
    }

    /// y = Σ_i c_i·x_i over four inputs (more than candle's three): packed path.
    struct WeightedSum4;
    impl Kernel for WeightedSum4 {
        fn name(&self) -> &'static str {
            "weighted_sum4"
        }
        fn output_shape(&self, s: &[&[usize]]) -> Result<Vec<usize>> {
            Ok(s[0].to_vec())
        }
        fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
            for (i, xi) in x.iter().enumerate() {
                let c = T::from_f64(i as f64 + 1.0);
                out.iter_mut().zip(xi.iter()).for_each(|(o, &v)| *o += c * v);
            }
            Ok(())
        }
        fn backward<T: Real>(&self, _: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
            for (i, gi) in grads.iter_mut().enumerate() {
                if let Some(gi) = gi.as_deref_mut() {
                    let c = T::from_f64(i as f64 + 1.0);
                    gi.iter_mut().zip(g).for_each(|(o, &v)| *o += c * v);
                }
            }
            Ok(())
        }
    }

    #[test]
    fn more_than_three_inputs_are_packed_transparently() -> Result<()> {
        let vars: Vec<Var> =
            (0..4).map(|i| Var::from_tensor(&Tensor::new(&[[i as f32, 1.0], [2.0, 3.0]], &Device::Cpu)?)).collect::<Result<_>>()?;
        let refs: Vec<&Tensor> = vars.iter().map(|v| v.as_tensor()).collect();
        let y = apply(WeightedSum4, &refs)?;
        assert_eq!(y.dims(), &[2, 2]);
        assert_eq!(y.to_vec2::<f32>()?[0], vec![1.0 * 0.0 + 2.0 * 1.0 + 3.0 * 2.0 + 4.0 * 3.0, 10.0]);
        let g = y.sum_all()?.backward()?;
        for (i, v) in vars.iter().enumerate() {
            let gi = g.get(v.as_tensor()).expect("grad").to_vec2::<f32>()?;
            assert_eq!(gi, vec![vec![i as f32 + 1.0; 2]; 2]);
        }
        Ok(())
    }

    #[test]
    fn no_grad_application_leaves_nothing_on_the_tape() -> Result<()> {
        let a = Var::new(&[1.0f32, 2.0], &Device::Cpu)?;
        let y = apply_no_grad(MulAddSquare, &[a.as_tensor(), a.as_tensor()])?;
        assert_eq!(y.to_vec1::<f32>()?, vec![2.0, 8.0]);
        assert!(!y.track_op());
        Ok(())
    }

    #[test]
    fn banded_scatter_matches_serial_and_any_band_count() {
        let n = 1000;
        let targets: Vec<usize> = (0..n).map(|i| (i * 7919) % 97).collect();
        let mut serial = vec![0.0f64; 97];
        for (i, &t) in targets.iter().enumerate() {
            serial[t] += i as f64 * 0.5;
            serial[(t + 1) % 97] += 1.0;
        }
        let mut par = vec![0.0f64; 97];
        scatter_add_banded(&mut par, n, |i, sink| {
            sink.add(targets[i], i as f64 * 0.5);
            sink.add((targets[i] + 1) % 97, 1.0);
        });
        assert_eq!(serial, par);
    }

    #[test]
    fn chunked_map_scatter_matches_serial_and_any_thread_count() {
        // Values whose sums round differently in different orders (1/3, 1e8), so a chunking that
        // followed the thread count would show.
        let n = 10_007;
        let target = |i: usize| (i * 7919) % 97;
        let value = |i: usize| if i.is_multiple_of(5) { 1e8 } else { (i as f64) / 3.0 };
        let mut serial = vec![0.0f64; 97];
        for i in 0..n {
            serial[target(i)] += value(i);
        }
        let run = |threads: usize| {
            let pool = rayon::ThreadPoolBuilder::new().num_threads(threads).build().expect("thread pool");
            pool.install(|| {
                map_scatter_chunked(n, 1000, 97, |i, sum| {
                    sum[target(i)] += value(i);
                    2 * i
                })
            })
        };
        let (results, sum) = run(1);
        assert_eq!(results, (0..n).map(|i| 2 * i).collect::<Vec<_>>(), "results in item order");
        for (a, b) in sum.iter().zip(&serial) {
            assert!((a - b).abs() <= 1e-12 * b.abs(), "{a} against the serial {b}");
        }
        for threads in [2, 3, 8] {
            assert_eq!(run(threads), (results.clone(), sum.clone()), "{threads} threads");
        }
        let (empty, zeros) = map_scatter_chunked(0, 1000, 4, |_, _| 0u8);
        assert!(empty.is_empty());
        assert_eq!(zeros, vec![0.0; 4]);
    }

    #[test]
    fn wrong_dtype_is_an_error_not_a_panic() -> Result<()> {
        let a = Tensor::new(&[1u32, 2], &Device::Cpu)?;
        assert!(apply(MulAddSquare, &[&a, &a]).is_err());
        let a = Tensor::new(&[1.0f32, 2.0], &Device::Cpu)?;
        let b = Tensor::new(&[1.0f32], &Device::Cpu)?;
        assert!(apply(MulAddSquare, &[&a, &b]).is_err());
        Ok(())
    }
}
