//! Material textures on the mesh's UV atlas: `kd` (linear base colour) and `ks` = (occlusion = 0,
//! roughness, metallic), NVDiffRec's layout. Baking from a per-part material gives ground truth
//! for evaluation and an oracle start for the optimiser.

use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::{Vec2, Vec3};
use rayon::prelude::*;

use crate::geometry::atlas::{texel_hits, Atlas};
use crate::geometry::tangents::corner_tangents;
use crate::geometry::Mesh;
use crate::image::io::{read_png, write_png};
use crate::image::Image;
use crate::material::normal_map::NormalMap;
use crate::material::SurfaceParams;

/// The normal map's file name beside `kd.png` and `ks.png`.
pub const NORMAL_FILE: &str = "normal.png";

/// Texels a bilinear lookup inside a chart can touch lie within √2 texels of it.
const CONSERVATIVE_REACH: f32 = 1.5;
/// Extra texels grown beyond the conservative coverage when baking (mip-mapping, jittered lookups).
const BAKE_DILATION: usize = 4;

#[derive(Clone, Debug, PartialEq)]
pub struct MaterialTextures {
    /// Linear base colour, [res, res, 3], row 0 at the top (v = 1).
    pub kd: Image,
    /// (occlusion = 0, roughness, metallic), [res, res, 3].
    pub ks: Image,
    /// A learned tangent-space normal map (`--normal-map`), in the atlas mesh's MikkTSpace frame.
    pub normal: Option<NormalMap>,
}

/// Bilinear lookup of an atlas texture at `uv` (OBJ convention: v up, so row 0 is v = 1; clamped
/// to [0, 1]), into `out` (one value per channel).
pub fn sample_atlas(image: &Image, uv: Vec2, out: &mut [f32]) {
    let (u, v) = (uv.x.clamp(0.0, 1.0), 1.0 - uv.y.clamp(0.0, 1.0));
    image.bilinear(u * image.width as f32, v * image.height as f32, out);
}

impl MaterialTextures {
    /// Uniform textures (the usual start of an optimisation).
    pub fn constant(res: usize, kd: Vec3, roughness: f32, metallic: f32) -> Self {
        MaterialTextures { kd: Image::filled(res, res, &kd.to_array()), ks: Image::filled(res, res, &[0.0, roughness, metallic]), normal: None }
    }

    pub fn resolution(&self) -> usize {
        self.kd.width
    }

    /// Rasterise every atlas triangle and evaluate the ORIGINAL mesh's part material at the
    /// barycentric-interpolated original UV. `mesh` is the mesh the atlas was built from (same
    /// triangle order).
    pub fn bake_from(mesh: &Mesh, atlas: &Atlas, res: usize) -> Result<Self> {
        if mesh.triangles.len() != atlas.mesh.triangles.len() {
            bail!("bake: the atlas has {} triangles but the material mesh has {}", atlas.mesh.triangles.len(), mesh.triangles.len());
        }
        mesh.validate().map_err(|e| anyhow::anyhow!("bake: invalid material mesh: {e}"))?;
        Ok(Self::bake_with(atlas, res, |t, bary| {
            let [a, b, c] = mesh.triangles[t].map(|i| mesh.uvs[i as usize]);
            mesh.triangle_material(t).eval(a * bary.x + b * bary.y + c * bary.z)
        }))
    }

    /// Rasterise every atlas triangle and fill each texel with `material(triangle, barycentrics
    /// (b0, b1, b2))` of the surface point it shows. Texels a bilinear lookup can touch are filled
    /// conservatively from the closest point of their chart; the rest of the border is dilated by
    /// a few texels.
    pub fn bake_with(atlas: &Atlas, res: usize, material: impl Fn(usize, Vec3) -> SurfaceParams + Sync) -> Self {
        let hits = texel_hits(&atlas.mesh, res, CONSERVATIVE_REACH);
        let mut kd = Image::new(res, res, 3);
        let mut ks = Image::new(res, res, 3);
        kd.data.par_chunks_mut(3).zip(ks.data.par_chunks_mut(3)).zip(hits.par_iter()).for_each(|((kd, ks), hit)| {
            if let Some(h) = hit {
                let p = material(h.triangle as usize, h.bary);
                kd.copy_from_slice(&p.kd.to_array());
                ks.copy_from_slice(&[0.0, p.roughness, p.metallic]);
            }
        });
        let mask: Vec<bool> = hits.iter().map(Option::is_some).collect();
        dilate(&mut kd, &mask, BAKE_DILATION);
        dilate(&mut ks, &mask, BAKE_DILATION);
        MaterialTextures { kd, ks, normal: None }
    }

    /// Bilinear lookup at an atlas UV (OBJ convention, v = 0 at the bottom row; clamped to the
    /// edge, not wrapped: an atlas does not tile).
    pub fn eval(&self, uv: Vec2) -> SurfaceParams {
        let (mut kd, mut ks) = ([0.0f32; 3], [0.0f32; 3]);
        sample_atlas(&self.kd, uv, &mut kd);
        sample_atlas(&self.ks, uv, &mut ks);
        SurfaceParams { kd: Vec3::from_array(kd), roughness: ks[1], metallic: ks[2] }
    }

    /// Write `kd.png` (sRGB-encoded) and `ks.png` (linear) into `dir` (created if missing), and
    /// with a normal map `normal.png` (tangent space, m·0.5 + 0.5, the glTF/Blender encoding).
    pub fn save(&self, dir: impl AsRef<Path>) -> Result<()> {
        let dir = dir.as_ref();
        std::fs::create_dir_all(dir).with_context(|| format!("cannot create texture folder {}", dir.display()))?;
        write_png(&dir.join("kd.png"), &self.kd.linear_to_srgb())?;
        write_png(&dir.join("ks.png"), &self.ks)?;
        if let Some(n) = &self.normal {
            let mut encoded = n.map.clone();
            encoded.data.iter_mut().for_each(|c| *c = *c * 0.5 + 0.5);
            write_png(&dir.join(NORMAL_FILE), &encoded)?;
        }
        Ok(())
    }

    /// Read textures written by `save` for the atlas mesh `mesh` they were learned on: the normal
    /// map too when `normal.png` is there (its frame is `mesh`'s MikkTSpace frame).
    pub fn load_for(dir: impl AsRef<Path>, mesh: &Mesh) -> Result<Self> {
        let dir = dir.as_ref();
        let mut t = Self::load(dir)?;
        let path = dir.join(NORMAL_FILE);
        if path.exists() {
            let mut map = read_png(&path)?;
            if map.channels != 3 || map.width != t.kd.width || map.height != t.kd.height {
                bail!("{}: expected an RGB normal map of {}², found {}x{} with {} channels", path.display(), t.kd.width, map.width, map.height, map.channels);
            }
            map.data.iter_mut().for_each(|c| *c = *c * 2.0 - 1.0);
            NormalMap::normalize_texels(&mut map.data);
            let tangents = corner_tangents(mesh).with_context(|| format!("the frame of {}", path.display()))?;
            t.normal = Some(NormalMap { map, tangents: tangents.into() });
        }
        Ok(t)
    }

    /// Read the kd and ks textures written by `save` (without the normal map, whose frame needs
    /// the mesh: [`MaterialTextures::load_for`]).
    pub fn load(dir: impl AsRef<Path>) -> Result<Self> {
        let dir = dir.as_ref();
        let rgb = |name: &str| -> Result<Image> {
            let path = dir.join(name);
            let img = read_png(&path)?;
            if img.channels != 3 {
                bail!("{}: expected an RGB texture, found {} channels", path.display(), img.channels);
            }
            if img.width != img.height {
                bail!("{}: expected a square texture, found {}x{}", path.display(), img.width, img.height);
            }
            Ok(img)
        };
        let kd = rgb("kd.png")?.srgb_to_linear();
        let ks = rgb("ks.png")?;
        if kd.width != ks.width {
            bail!("{}: kd.png is {}² but ks.png is {}²", dir.display(), kd.width, ks.width);
        }
        Ok(MaterialTextures { kd, ks, normal: None })
    }
}

/// Grow the texels marked in `mask` outward by `texels` rings: each new texel takes the mean of
/// its already-filled 8-neighbours. Filled texels never change, so dilation cannot bleed one
/// chart's values into another's texels.
pub fn dilate(img: &mut Image, mask: &[bool], texels: usize) {
    assert_eq!(mask.len(), img.pixel_count(), "dilate: mask and image sizes differ");
    let (w, h, ch) = (img.width, img.height, img.channels);
    let mut filled = mask.to_vec();
    for _ in 0..texels {
        let grown: Vec<(usize, Vec<f32>)> = (0..w * h)
            .into_par_iter()
            .filter(|&i| !filled[i])
            .filter_map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                let mut sum = vec![0.0f32; ch];
                let mut n = 0;
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (nx, ny) = (x + dx, y + dy);
                        if nx < 0 || ny < 0 || nx >= w as isize || ny >= h as isize {
                            continue;
                        }
                        let j = ny as usize * w + nx as usize;
                        if filled[j] {
                            n += 1;
                            for (s, v) in sum.iter_mut().zip(&img.data[j * ch..(j + 1) * ch]) {
                                *s += v;
                            }
                        }
                    }
                }
                (n > 0).then(|| (i, sum.into_iter().map(|s| s / n as f32).collect()))
            })
            .collect();
        if grown.is_empty() {
            break;
        }
        for (i, v) in grown {
            img.data[i * ch..(i + 1) * ch].copy_from_slice(&v);
            filled[i] = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dilate_grows_rings_and_keeps_filled_texels() {
        let mut img = Image::new(7, 7, 1);
        let mut mask = vec![false; 49];
        img.data[3 * 7 + 3] = 2.0;
        mask[3 * 7 + 3] = true;
        img.data[0] = 9.0; // not in the mask: must be overwritten only if reached
        dilate(&mut img, &mask, 2);
        // Two rings around the centre: a 5x5 block of 2.0.
        for y in 0..7 {
            for x in 0..7 {
                let inside = (1..=5).contains(&x) && (1..=5).contains(&y);
                let v = img.pixel(x, y)[0];
                if inside {
                    assert_eq!(v, 2.0, "texel {x},{y}");
                } else if (x, y) != (0, 0) {
                    assert_eq!(v, 0.0, "texel {x},{y}");
                }
            }
        }
        assert_eq!(img.pixel(0, 0)[0], 9.0);
    }

    #[test]
    fn eval_follows_the_obj_convention() {
        // Top row red, bottom row blue: v = 1 is the top.
        let mut t = MaterialTextures::constant(2, Vec3::ZERO, 0.5, 0.0);
        for x in 0..2 {
            t.kd.pixel_mut(x, 0).copy_from_slice(&[1.0, 0.0, 0.0]);
            t.kd.pixel_mut(x, 1).copy_from_slice(&[0.0, 0.0, 1.0]);
        }
        assert_eq!(t.eval(Vec2::new(0.5, 0.99)).kd, Vec3::X);
        assert_eq!(t.eval(Vec2::new(0.5, 0.01)).kd, Vec3::Z);
        let mid = t.eval(Vec2::new(0.5, 0.5));
        assert!((mid.kd - Vec3::new(0.5, 0.0, 0.5)).abs().max_element() < 1e-6);
        assert_eq!((mid.roughness, mid.metallic), (0.5, 0.0));
    }
}
