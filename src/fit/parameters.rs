//! The optimised parameters: kd and ks textures on the UV atlas, the base cube map of the light and,
//! with `--normal-map`, a tangent-space normal map, as candle `Var`s (f32), with conversions to the
//! renderer's plain types.

use anyhow::{bail, Result};
use candle_core::{DType, Device, Tensor, Var};
use std::sync::Arc;

use glam::{Vec3, Vec4};

use crate::image::Image;
use crate::light::CubeMap;
use crate::material::normal_map::NormalMap;
use crate::material::texture_maps::MaterialTextures;

use super::config::FitConfig;

pub struct Parameters {
    /// Linear base colour [T, T, 3], row 0 at the top (v = 1), like `MaterialTextures::kd`.
    pub kd: Var,
    /// (occlusion, roughness, metallic) [T, T, 3].
    pub ks: Var,
    /// Base cube map [6, R, R, 3] (OpenGL face order, `CubeMap::data` order).
    pub light: Var,
    /// Tangent-space normal map [T, T, 3] and the atlas mesh's corner frames it lives in.
    pub normal: Option<NormalParameter>,
}

/// The normal map's name: its optimiser group and its tensor in a checkpoint.
pub const NORMAL_NAME: &str = "normal";

pub struct NormalParameter {
    pub map: Var,
    pub tangents: Arc<[[Vec4; 3]]>,
}

impl NormalParameter {
    pub fn from_map(n: &NormalMap) -> Result<NormalParameter> {
        Ok(NormalParameter { map: Var::from_tensor(&image_tensor(&n.map)?)?, tangents: n.tangents.clone() })
    }

    /// Each texel back to unit length (after an optimiser step).
    pub fn normalize(&self) -> Result<()> {
        let t = self.map.as_tensor();
        let mut data = t.flatten_all()?.to_vec1::<f32>()?;
        NormalMap::normalize_texels(&mut data);
        self.map.set(&Tensor::from_vec(data, t.dims(), t.device())?)?;
        Ok(())
    }
}

fn image_tensor(img: &Image) -> Result<Tensor> {
    Ok(Tensor::from_slice(&img.data, (img.height, img.width, img.channels), &Device::Cpu)?)
}

fn tensor_image(t: &Tensor) -> Result<Image> {
    let (h, w, c) = t.dims3()?;
    let data = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    Ok(Image { width: w, height: h, channels: c, data })
}

/// A cube map as a [6, R, R, 3] tensor.
pub fn cube_tensor(cube: &CubeMap) -> Result<Tensor> {
    let flat: Vec<f32> = cube.data.iter().flat_map(|v| v.to_array()).collect();
    Ok(Tensor::from_vec(flat, (6, cube.res, cube.res, 3), &Device::Cpu)?)
}

/// A [6, R, R, 3] tensor as a cube map.
pub fn tensor_cube(t: &Tensor) -> Result<CubeMap> {
    let dims = t.dims();
    if dims.len() != 4 || dims[0] != 6 || dims[1] != dims[2] || dims[3] != 3 {
        bail!("a cube map tensor must be [6, R, R, 3], got {dims:?}");
    }
    let flat = t.to_dtype(DType::F32)?.flatten_all()?.to_vec1::<f32>()?;
    Ok(CubeMap { res: dims[1], data: flat.chunks_exact(3).map(|c| Vec3::new(c[0], c[1], c[2])).collect() })
}

impl Parameters {
    /// Constant start values of `config`.
    pub fn initial(config: &FitConfig) -> Result<Parameters> {
        let t = MaterialTextures::constant(config.texture_res, Vec3::splat(config.init_kd), config.init_roughness, config.init_metallic);
        let light = CubeMap::constant(config.light_res, Vec3::splat(config.init_light));
        Parameters::from_values(&t, &light)
    }

    pub fn from_values(textures: &MaterialTextures, light: &CubeMap) -> Result<Parameters> {
        Ok(Parameters {
            kd: Var::from_tensor(&image_tensor(&textures.kd)?)?,
            ks: Var::from_tensor(&image_tensor(&textures.ks)?)?,
            light: Var::from_tensor(&cube_tensor(light)?)?,
            normal: textures.normal.as_ref().map(NormalParameter::from_map).transpose()?,
        })
    }

    pub fn textures(&self) -> Result<MaterialTextures> {
        let normal = match &self.normal {
            Some(n) => Some(NormalMap { map: tensor_image(n.map.as_tensor())?, tangents: n.tangents.clone() }),
            None => None,
        };
        Ok(MaterialTextures { kd: tensor_image(self.kd.as_tensor())?, ks: tensor_image(self.ks.as_tensor())?, normal })
    }

    /// The optimised tensors, named (the checkpoint's and the optimiser's names).
    pub fn named(&self) -> Vec<(&'static str, &Var)> {
        let mut v = vec![("kd", &self.kd), ("ks", &self.ks), ("light", &self.light)];
        if let Some(n) = &self.normal {
            v.push((NORMAL_NAME, &n.map));
        }
        v
    }

    pub fn light_cube(&self) -> Result<CubeMap> {
        tensor_cube(self.light.as_tensor())
    }

    /// True when every value is finite (a diverged run is caught before it is saved).
    pub fn all_finite(&self) -> Result<bool> {
        for (_, v) in self.named() {
            let flat = v.as_tensor().flatten_all()?.to_vec1::<f32>()?;
            if flat.iter().any(|x| !x.is_finite()) {
                return Ok(false);
            }
        }
        Ok(true)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_normal_map_round_trips_with_its_frames() -> Result<()> {
        let mut t = MaterialTextures::constant(2, Vec3::splat(0.5), 0.5, 0.0);
        let frames: Arc<[[Vec4; 3]]> = vec![[Vec4::new(1.0, 0.0, 0.0, -1.0); 3]].into();
        let mut n = NormalMap::flat(2, frames);
        n.map.data[0..3].copy_from_slice(&[0.6, 0.0, 0.8]);
        t.normal = Some(n);
        let p = Parameters::from_values(&t, &CubeMap::constant(2, Vec3::ONE))?;
        assert_eq!(p.named().iter().map(|(k, _)| *k).collect::<Vec<_>>(), ["kd", "ks", "light", "normal"]);
        assert_eq!(p.textures()?, t);
        Ok(())
    }

    #[test]
    fn textures_and_light_round_trip_through_tensors() -> Result<()> {
        let light = CubeMap::from_fn(3, |d| Vec3::new(d.x.abs(), d.y.max(0.0), 2.0 + d.z));
        let mut t = MaterialTextures::constant(4, Vec3::new(0.1, 0.2, 0.3), 0.4, 0.5);
        t.kd.data[5] = 0.9;
        let p = Parameters::from_values(&t, &light)?;
        assert_eq!(p.textures()?, t);
        let back = p.light_cube()?;
        assert_eq!(back.res, 3);
        assert_eq!(back.data, light.data);
        Ok(())
    }
}
