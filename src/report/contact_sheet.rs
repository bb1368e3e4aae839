//! A contact sheet: renders laid out in a grid on white, each with its caption underneath.

use plotters::prelude::*;

use crate::color::linear_to_srgb;
use crate::image::Image;
use super::plot::{register_font, FAMILY};

/// Caption strip height in pixels.
const CAPTION: usize = 20;

/// `tiles`: (caption, linear RGB or straight-alpha RGBA image, composited over white) placed
/// left to right, top to bottom, `columns` per row, each resized (bilinear) to fit a
/// `tile_size`² cell. Returns an sRGB-encoded RGB image ready for `write_png`.
pub fn contact_sheet(tiles: &[(String, Image)], columns: usize, tile_size: usize) -> Image {
    register_font();
    let columns = columns.max(1);
    let rows = tiles.len().div_ceil(columns).max(1);
    let (cell_w, cell_h) = (tile_size, tile_size + CAPTION);
    let (w, h) = (columns * cell_w, rows * cell_h);
    let mut buf = vec![255u8; w * h * 3];
    for (k, (_, img)) in tiles.iter().enumerate() {
        let (ox, oy) = ((k % columns) * cell_w, (k / columns) * cell_h);
        let scale = (img.width.max(img.height) as f32 / tile_size as f32).max(1e-6);
        let mut px = vec![0.0f32; img.channels];
        for y in 0..tile_size {
            for x in 0..tile_size {
                let (sx, sy) = ((x as f32 + 0.5) * scale, (y as f32 + 0.5) * scale);
                if sx >= img.width as f32 || sy >= img.height as f32 {
                    continue;
                }
                img.bilinear(sx, sy, &mut px);
                let alpha = if img.channels == 4 { px[3].clamp(0.0, 1.0) } else { 1.0 };
                let o = 3 * ((oy + y) * w + ox + x);
                for c in 0..3 {
                    let v = if img.channels == 1 { px[0] } else { px[c.min(img.channels - 1)] };
                    let srgb = linear_to_srgb(v.clamp(0.0, 1.0)) * alpha + (1.0 - alpha);
                    buf[o + c] = (srgb * 255.0).round() as u8;
                }
            }
        }
    }
    {
        let root = BitMapBackend::with_buffer(&mut buf, (w as u32, h as u32)).into_drawing_area();
        for (k, (caption, _)) in tiles.iter().enumerate() {
            let (ox, oy) = ((k % columns) * cell_w, (k / columns) * cell_h + tile_size);
            // Text is decoration: a drawing failure leaves the caption out, not the sheet.
            let _ = root.draw(&Text::new(caption.clone(), (ox as i32 + 4, oy as i32 + 3), (FAMILY, 13)));
        }
        let _ = root.present();
    }
    Image { width: w, height: h, channels: 3, data: buf.iter().map(|&b| b as f32 / 255.0).collect() }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tiles_land_in_their_grid_cells() {
        let colours = [[1.0f32, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let tiles: Vec<(String, Image)> = colours.iter().enumerate().map(|(k, c)| (format!("t{k}"), Image::filled(8, 8, c))).collect();
        let sheet = contact_sheet(&tiles, 2, 16);
        assert_eq!((sheet.width, sheet.height, sheet.channels), (32, 2 * (16 + CAPTION), 3));
        for (k, c) in colours.iter().enumerate() {
            let (x, y) = ((k % 2) * 16 + 8, (k / 2) * (16 + CAPTION) + 8);
            assert_eq!(sheet.pixel(x, y), c, "tile {k}");
        }
        // The empty fourth cell stays white.
        assert_eq!(sheet.pixel(24, 16 + CAPTION + 8), &[1.0, 1.0, 1.0]);
    }
}
