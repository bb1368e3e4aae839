//! Moving per-covered-pixel rows ([n, C]) into a full image ([H, W, C], zero elsewhere) and back,
//! on the tape: the image-space denoiser needs neighbourhoods, the loss works on pixel lists.
//! Scatter and gather are each other's transpose, so each one's backward is the other's forward.
//! `composite` is the scatter the geometry pass renders with: colour rows onto a background colour,
//! with coverage (1 on the rows' pixels, 0 elsewhere) as an extra channel.

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
/// Rows [n, C] → image [H·W, C + 1]: (row, 1) on the map's pixels, (background, 0) elsewhere.
#[derive(Clone)]
struct Composite {
    map: PixelMap,
    background: Vec<f32>,
}

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

impl Kernel for Composite {
    fn name(&self) -> &'static str {
        "pixel_composite"
    }
    fn output_shape(&self, shapes: &[&[usize]]) -> Result<Vec<usize>> {
        match shapes {
            [[n, c]] if *n == self.map.pixels.len() && *c == self.background.len() => Ok(vec![self.map.width * self.map.height, c + 1]),
            _ => Err(candle_core::Error::Msg(format!(
                "pixel composite: expected [{}, {}], got {shapes:?}",
                self.map.pixels.len(),
                self.background.len()
            ))),
        }
    }
    fn forward<T: Real>(&self, x: &[&[T]], _: &[&[usize]], out: &mut [T]) -> Result<()> {
        let c = self.background.len();
        let bg: Vec<T> = self.background.iter().map(|&v| T::from_f64(v as f64)).chain([T::zero()]).collect();
        out.par_chunks_mut(c + 1).for_each(|px| px.copy_from_slice(&bg));
        let rows = x[0];
        for (k, &p) in self.map.pixels.iter().enumerate() {
            let px = &mut out[(c + 1) * p as usize..(c + 1) * (p as usize + 1)];
            px[..c].copy_from_slice(&rows[c * k..c * (k + 1)]);
            px[c] = T::one();
        }
        Ok(())
    }
    fn backward<T: Real>(&self, _x: &[&[T]], _: &[&[usize]], g: &[T], grads: &mut [Option<&mut [T]>]) -> Result<()> {
        let c = self.background.len();
        if let Some(gx) = grads[0].as_deref_mut() {
            gx.par_chunks_mut(c).zip(self.map.pixels.par_iter()).for_each(|(r, &p)| {
                for (a, b) in r.iter_mut().zip(&g[(c + 1) * p as usize..(c + 1) * p as usize + c]) {
                    *a += *b;
                }
            });
        }
        Ok(())
    }
}

impl PixelMap {
    /// [n, C] rows → [H, W, C] image.
    pub fn scatter(&self, rows: &Tensor) -> Result<Tensor> {
        apply(Scatter(self.clone()), &[rows])
    }
    /// [n, C] rows → [H·W, C + 1] image: each row and coverage 1 on its pixel, `background` and
    /// coverage 0 elsewhere (C = `background.len()`).
    pub fn composite(&self, rows: &Tensor, background: &[f32]) -> Result<Tensor> {
        apply(Composite { map: self.clone(), background: background.to_vec() }, &[rows])
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
        let over = map().composite(&rows, &[0.5, 0.25])?.to_vec2::<f32>()?;
        assert_eq!(over[5], vec![1.0, 2.0, 1.0]);
        assert_eq!(over[1], vec![0.5, 0.25, 0.0]);
        Ok(())
    }

    #[test]
    fn a_view_the_mesh_misses_composites_to_the_background() -> Result<()> {
        // No covered pixel (the geometry pass's view that sees none of the mesh): [0, C] rows.
        let none = PixelMap { pixels: Vec::new().into(), width: 3, height: 2 };
        let rows = candle_core::Var::from_tensor(&Tensor::zeros((0, 2), candle_core::DType::F32, &Device::Cpu)?)?;
        let over = none.composite(rows.as_tensor(), &[0.5, 0.25])?;
        assert_eq!(over.to_vec2::<f32>()?, vec![vec![0.5, 0.25, 0.0]; 6]);
        let g = over.sum_all()?.backward()?;
        assert_eq!(g.get(rows.as_tensor()).map(|t| t.elem_count()), Some(0));
        Ok(())
    }

    #[test]
    fn gradients_match_finite_differences() -> anyhow::Result<()> {
        let rows = Tensor::rand(0f64, 1.0, (4, 3), &Device::Cpu)?;
        let w = Tensor::rand(0f64, 1.0, (3, 3, 3), &Device::Cpu)?;
        check_gradient(|x| (map().scatter(&x[0])? * &w)?.sum_all(), std::slice::from_ref(&rows), 1e-6, 1e-2)?;
        let img = Tensor::rand(0f64, 1.0, (3, 3, 3), &Device::Cpu)?;
        let w = Tensor::rand(0f64, 1.0, (4, 3), &Device::Cpu)?;
        check_gradient(|x| (map().gather(&x[0])? * &w)?.sum_all(), &[img], 1e-6, 1e-2)?;
        let w = Tensor::rand(0f64, 1.0, (9, 4), &Device::Cpu)?;
        check_gradient(|x| (map().composite(&x[0], &[0.2, 0.5, 0.9])? * &w)?.sum_all(), &[rows], 1e-6, 1e-2)?;
        Ok(())
    }
}
