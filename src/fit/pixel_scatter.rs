//! Moving per-covered-pixel rows ([n, C]) into a full image ([H, W, C], zero elsewhere) and back,
//! on the tape: the image-space denoiser needs neighbourhoods, the loss works on pixel lists.
//! Scatter and gather are each other's transpose, so each one's backward is the other's forward.

use std::sync::Arc;

use candle_core::{Result, Tensor};
use rayon::prelude::*;

use crate::optim::tape::{apply, Kernel, Real};

/// Rows ↔ image for one view: `pixels[k]` is the image index (y·W + x) of row k (distinct).
#[derive(Clone)]
pub struct PixelMap {
    pub pixels: Arc<[u32]>,
    pub width: usize,
    pub height: usize,
}

#[derive(Clone)]
struct Scatter(PixelMap);
#[derive(Clone)]
struct Gather(PixelMap);

fn scatter_rows<T: Real>(map: &PixelMap, rows: &[T], image: &mut [T], c: usize) {
    // Distinct pixels: every image row is written by at most one source row, so a lookup table
    // from image index to row keeps the write parallel and race-free.
    let mut row_of = vec![u32::MAX; map.width * map.height];
    for (k, &p) in map.pixels.iter().enumerate() {
        row_of[p as usize] = k as u32;
    }
    image.par_chunks_mut(c).zip(row_of.par_iter()).for_each(|(px, &k)| {
        if k != u32::MAX {
            let k = k as usize;
            for (a, b) in px.iter_mut().zip(&rows[c * k..c * (k + 1)]) {
                *a += *b;
            }
        }
    });
}

fn gather_rows<T: Real>(map: &PixelMap, image: &[T], rows: &mut [T], c: usize) {
    rows.par_chunks_mut(c).zip(map.pixels.par_iter()).for_each(|(r, &p)| {
        let p = p as usize;
        for (a, b) in r.iter_mut().zip(&image[c * p..c * (p + 1)]) {
            *a += *b;
        }
    });
}

impl Kernel for Scatter {
    fn name(&self) -> &'static str {
        "pixel_scatter"
    }
    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[n, c]] if *n == self.0.pixels.len() => Ok(vec![self.0.height, self.0.width, *c]),
            _ => Err(candle_core::Error::Msg(format!("pixel scatter: expected [{}, C], got {shapes:?}", self.0.pixels.len()))),
        }
    }
    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        scatter_rows(&self.0, x[0], out, shapes[0][1]);
        Ok(())
    }
    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        if let Some(gx) = grads[0].as_deref_mut() {
            gather_rows(&self.0, g, gx, shapes[0][1]);
        }
        Ok(())
    }
}

impl Kernel for Gather {
    fn name(&self) -> &'static str {
        "pixel_gather"
    }
    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[h, w, c]] if *h == self.0.height && *w == self.0.width => Ok(vec![self.0.pixels.len(), *c]),
            _ => Err(candle_core::Error::Msg(format!("pixel gather: expected [{}, {}, C], got {shapes:?}", self.0.height, self.0.width))),
        }
    }
    fn forward<T: Real>(&self, x: &[&[T]], shapes: &[&[usize]], out: &mut [T]) -> Result<()> {
        gather_rows(&self.0, x[0], out, shapes[0][2]);
        Ok(())
    }
    fn backward<T: Real>(&self, _x: &[&[T]], shapes: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        if let Some(gx) = grads[0].as_deref_mut() {
            scatter_rows(&self.0, g, gx, shapes[0][2]);
        }
        Ok(())
    }
}

impl PixelMap {
    /// [n, C] rows → [H, W, C] image.
    pub fn scatter(&self, rows: &Tensor) -> Result<Tensor> {
        apply(Scatter(self.clone()), &[rows])
    }
    /// [H, W, C] image → [n, C] rows.
    pub fn gather(&self, image: &Tensor) -> Result<Tensor> {
        apply(Gather(self.clone()), &[image])
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::optim::gradcheck::check_gradient;
    use candle_core::Device;

    fn map() -> PixelMap {
        PixelMap { pixels: vec![5u32, 0, 7, 2].into(), width: 3, height: 3 }
    }

    #[test]
    fn scatter_then_gather_is_the_identity_and_fills_zeros_elsewhere() -> Result<()> {
        let rows = Tensor::new(&[[1f32, 2.0], [3.0, 4.0], [5.0, 6.0], [7.0, 8.0]], &Device::Cpu)?;
        let img = map().scatter(&rows)?;
        let flat = img.flatten_all()?.to_vec1::<f32>()?;
        assert_eq!(&flat[10..12], &[1.0, 2.0]); // pixel 5
        assert_eq!(&flat[0..2], &[3.0, 4.0]); // pixel 0
        assert_eq!(&flat[2..4], &[0.0, 0.0]); // pixel 1: not covered
        assert_eq!(map().gather(&img)?.to_vec2::<f32>()?, rows.to_vec2::<f32>()?);
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let rows = Tensor::rand(0f64, 1.0, (4, 3), &Device::Cpu)?;
        let w = Tensor::rand(0f64, 1.0, (3, 3, 3), &Device::Cpu)?;
        check_gradient(|x| (map().scatter(&x[0])? * &w)?.sum_all(), &[rows], 1e-6, 1e-2)?;
        let img = Tensor::rand(0f64, 1.0, (3, 3, 3), &Device::Cpu)?;
        let w = Tensor::rand(0f64, 1.0, (4, 3), &Device::Cpu)?;
        check_gradient(|x| (map().gather(&x[0])? * &w)?.sum_all(), &[img], 1e-6, 1e-2)?;
        Ok(())
    }
}
