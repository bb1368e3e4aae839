//! Reused per-thread f32 work buffers for the UNet's CPU kernels. A large buffer allocated fresh
//! for every call is handed out by the kernel page by page, each page zeroed on first touch: that
//! page-fault work was 30–40 % of a UNet forward when every attention layer allocated its scores.
use std::cell::RefCell;

thread_local! {
    static POOL: RefCell<Vec<Vec<f32>>> = const { RefCell::new(Vec::new()) };
}

/// A buffer taken from this thread's pool and returned to it on drop. Its contents are left over
/// from earlier use: callers overwrite what they read.
pub struct Scratch {
    buf: Vec<f32>,
    len: usize,
}

impl Scratch {
    /// A buffer of at least `len` elements (nested takes get distinct buffers).
    pub fn take(len: usize) -> Self {
        let mut buf = POOL.with(|p| p.borrow_mut().pop()).unwrap_or_default();
        if buf.len() < len {
            buf.resize(len, 0.0);
        }
        Self { buf, len }
    }

    pub fn as_mut_slice(&mut self) -> &mut [f32] {
        &mut self.buf[..self.len]
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let buf = std::mem::take(&mut self.buf);
        POOL.with(|p| p.borrow_mut().push(buf));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Nested takes must not share memory; a returned buffer is reused.
    #[test]
    fn nested_buffers_are_distinct_and_reused() {
        let mut a = Scratch::take(16);
        let mut b = Scratch::take(16);
        assert_ne!(a.as_mut_slice().as_ptr(), b.as_mut_slice().as_ptr());
        let pa = a.as_mut_slice().as_ptr();
        drop(b);
        drop(a);
        let mut c = Scratch::take(8);
        assert_eq!(c.as_mut_slice().as_ptr(), pa);
        assert_eq!(c.as_mut_slice().len(), 8);
    }
}
