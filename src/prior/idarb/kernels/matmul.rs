//! f32 matrix products on strided views, straight through the `gemm` crate (candle's own CPU
//! matmul backend, here with its AVX-512 kernels on): the UNet's kernels multiply head slices,
//! transposed keys and im2col buffers where they lie, without the contiguous copies and fresh
//! output tensors `Tensor::matmul` needs.
use gemm::Parallelism;

/// A strided matrix view: element (i, j) is `data[i·rs + j·cs]`.
#[derive(Debug, Clone, Copy)]
pub struct MatRef<'a> {
    data: &'a [f32],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

/// The writable counterpart of [`MatRef`].
#[derive(Debug)]
pub struct MatMut<'a> {
    data: &'a mut [f32],
    rows: usize,
    cols: usize,
    rs: usize,
    cs: usize,
}

/// Panics unless every element of a `rows × cols` view with strides (rs, cs) lies in `len`: the
/// bounds check that makes the raw-pointer product below sound.
fn check_extent(len: usize, rows: usize, cols: usize, rs: usize, cs: usize) {
    if rows > 0 && cols > 0 {
        let last = (rows - 1) * rs + (cols - 1) * cs;
        assert!(last < len, "matrix view {rows}×{cols} (strides {rs}, {cs}) overruns a buffer of {len}");
    }
}

impl<'a> MatRef<'a> {
    pub fn new(data: &'a [f32], rows: usize, cols: usize, rs: usize, cs: usize) -> Self {
        check_extent(data.len(), rows, cols, rs, cs);
        Self { data, rows, cols, rs, cs }
    }

    /// The transpose, as a view of the same data.
    pub fn t(self) -> Self {
        Self { rows: self.cols, cols: self.rows, rs: self.cs, cs: self.rs, ..self }
    }
}

impl<'a> MatMut<'a> {
    pub fn new(data: &'a mut [f32], rows: usize, cols: usize, rs: usize, cs: usize) -> Self {
        check_extent(data.len(), rows, cols, rs, cs);
        Self { data, rows, cols, rs, cs }
    }
}

/// `dst ← alpha · lhs · rhs`, or `dst ← dst + alpha · lhs · rhs` when `accumulate`. `parallel`
/// lets gemm split the product over rayon's threads (off inside tasks that are already parallel).
pub fn gemm(dst: MatMut, lhs: MatRef, rhs: MatRef, alpha: f32, accumulate: bool, parallel: bool) {
    let (m, n, k) = (dst.rows, dst.cols, lhs.cols);
    assert!(lhs.rows == m && rhs.rows == k && rhs.cols == n, "gemm: {}×{} · {}×{} into {m}×{n}", lhs.rows, k, rhs.rows, rhs.cols);
    if m == 0 || n == 0 {
        return;
    }
    if k == 0 {
        if !accumulate {
            for i in 0..m {
                for j in 0..n {
                    dst.data[i * dst.rs + j * dst.cs] = 0.0;
                }
            }
        }
        return;
    }
    let parallelism = match rayon::current_num_threads() {
        t if parallel && t > 1 => Parallelism::Rayon(t),
        _ => Parallelism::None,
    };
    // SAFETY: every view was checked to lie inside its slice, and `dst` is borrowed mutably, so it
    // cannot alias `lhs` or `rhs`.
    unsafe {
        gemm::gemm(
            m,
            n,
            k,
            dst.data.as_mut_ptr(),
            dst.cs as isize,
            dst.rs as isize,
            accumulate,
            lhs.data.as_ptr(),
            lhs.cs as isize,
            lhs.rs as isize,
            rhs.data.as_ptr(),
            rhs.cs as isize,
            rhs.rs as isize,
            1.0,
            alpha,
            false,
            false,
            false,
            parallelism,
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn naive(a: &[f32], b: &[f32], m: usize, k: usize, n: usize) -> Vec<f32> {
        let mut c = vec![0f32; m * n];
        for i in 0..m {
            for j in 0..n {
                c[i * n + j] = (0..k).map(|p| a[i * k + p] * b[p * n + j]).sum();
            }
        }
        c
    }

    /// Transposed and strided operands, scaling and accumulation against a triple loop.
    #[test]
    fn strided_product_matches_triple_loop() {
        let (m, k, n) = (7usize, 5usize, 9usize);
        let a: Vec<f32> = (0..m * k).map(|i| (i as f32 * 0.37).sin()).collect();
        let b: Vec<f32> = (0..k * n).map(|i| (i as f32 * 0.21).cos()).collect();
        let want = naive(&a, &b, m, k, n);
        // b stored transposed (n × k), a embedded with a row stride of k + 3
        let bt: Vec<f32> = (0..n * k).map(|i| b[(i % k) * n + i / k]).collect();
        let mut a_pad = vec![f32::NAN; m * (k + 3)];
        for i in 0..m {
            a_pad[i * (k + 3)..i * (k + 3) + k].copy_from_slice(&a[i * k..(i + 1) * k]);
        }
        let mut c = vec![1f32; m * n];
        gemm(MatMut::new(&mut c, m, n, n, 1), MatRef::new(&a_pad, m, k, k + 3, 1), MatRef::new(&bt, n, k, k, 1).t(), 0.5, true, true);
        for (g, w) in c.iter().zip(&want) {
            assert!((g - (1.0 + 0.5 * w)).abs() < 1e-5, "{g} vs {}", 1.0 + 0.5 * w);
        }
    }

    #[test]
    #[should_panic(expected = "overruns")]
    fn rejects_a_view_past_the_buffer() {
        let data = [0f32; 10];
        MatRef::new(&data, 3, 4, 4, 1);
    }
}
