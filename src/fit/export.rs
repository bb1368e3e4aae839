//! Writing a fitted model: the mesh with its material textures (OBJ + MTL and glTF, for Blender
//! and other tools), the textures alone, and the light as a lat-long EXR plus the six cube faces.

use std::path::Path;

use anyhow::{Context, Result};
use glam::Vec3;

use crate::geometry::gltf_io::write_gltf;
use crate::geometry::mesh::Part;
use crate::geometry::obj::{write_obj, MaterialTextureNames};
use crate::geometry::Mesh;
use crate::image::io::{write_exr, write_png};
use crate::image::Image;
use crate::light::CubeMap;
use crate::material::{BaseColor, PartMaterial, Scalar};
use crate::material::texture_maps::{MaterialTextures, NORMAL_FILE};

/// Cube faces in `CubeMap` order (OpenGL: +x, −x, +y, −y, +z, −z).
pub const FACE_NAMES: [&str; 6] = ["px", "nx", "py", "ny", "pz", "nz"];
/// Size of the exported lat-long light (width; height is half).
pub const LATLONG_WIDTH: usize = 512;

/// The atlas mesh as one part with one material whose constants are the textures' means (the
/// textures carry the detail).
pub fn single_material_mesh(atlas_mesh: &Mesh, textures: &MaterialTextures) -> Mesh {
    let mean = |img: &Image, c: usize| img.data.chunks_exact(img.channels).map(|p| p[c] as f64).sum::<f64>() / img.pixel_count().max(1) as f64;
    let material = PartMaterial {
        name: "learned".into(),
        base_color: BaseColor::Constant(Vec3::new(mean(&textures.kd, 0) as f32, mean(&textures.kd, 1) as f32, mean(&textures.kd, 2) as f32)),
        roughness: Scalar::Constant(mean(&textures.ks, 1) as f32),
        metallic: Scalar::Constant(mean(&textures.ks, 2) as f32),
    };
    Mesh {
        positions: atlas_mesh.positions.clone(),
        normals: atlas_mesh.normals.clone(),
        uvs: atlas_mesh.uvs.clone(),
        triangles: atlas_mesh.triangles.clone(),
        triangle_part: vec![0; atlas_mesh.triangles.len()],
        parts: vec![Part { name: "learned".into(), material: 0, has_uv: true }],
        materials: vec![material],
    }
}

/// `dir/model.obj` (+ .mtl), `dir/model.gltf` (+ .bin), `kd.png` (sRGB), `ks.png` (linear ORM:
/// G = roughness, B = metallic), `roughness.png` and `metallic.png` (grey, for the MTL).
pub fn write_model(dir: &Path, atlas_mesh: &Mesh, textures: &MaterialTextures) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    textures.save(dir)?;
    write_png(&dir.join("roughness.png"), &textures.ks.channel(1))?;
    write_png(&dir.join("metallic.png"), &textures.ks.channel(2))?;
    let mesh = single_material_mesh(atlas_mesh, textures);
    let names = MaterialTextureNames {
        base_color: Some("kd.png".into()),
        roughness: Some("roughness.png".into()),
        metallic: Some("metallic.png".into()),
        occlusion_roughness_metallic: Some("ks.png".into()),
        normal: textures.normal.as_ref().map(|_| NORMAL_FILE.to_string()),
    };
    write_obj(dir.join("model.obj"), &mesh, std::slice::from_ref(&names))?;
    write_gltf(dir.join("model.gltf"), &mesh, &[names])
}

/// `dir/light_latlong.exr` and `dir/light_<face>.exr` for each cube face.
pub fn write_light(dir: &Path, light: &CubeMap) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    write_exr(&dir.join("light_latlong.exr"), &light.to_latlong(LATLONG_WIDTH, LATLONG_WIDTH / 2))?;
    let r = light.res;
    for (f, name) in FACE_NAMES.iter().enumerate() {
        let mut img = Image::new(r, r, 3);
        for i in 0..r {
            for j in 0..r {
                img.set_rgb(i * r + j, light.data[light.texel_index(f, i, j)]);
            }
        }
        write_exr(&dir.join(format!("light_{name}.exr")), &img)?;
    }
    Ok(())
}

/// A view's learned material maps as PNGs: `<view>_kd.png` (sRGB), `<view>_roughness.png` and
/// `<view>_metallic.png` (linear), beside its renders.
pub fn write_material_maps(dir: &Path, maps: &crate::eval::protocol::MaterialMaps) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    write_png(&dir.join(format!("{}_kd.png", maps.view)), &maps.kd.map_channels(3, |v| crate::color::linear_to_srgb(v.clamp(0.0, 1.0))))?;
    write_png(&dir.join(format!("{}_roughness.png", maps.view)), &maps.roughness)?;
    write_png(&dir.join(format!("{}_metallic.png", maps.view)), &maps.metallic)
}

/// A linear RGBA render as `stem.png` (sRGB) and `stem.exr` (linear).
pub fn write_render(dir: &Path, stem: &str, img: &Image) -> Result<()> {
    std::fs::create_dir_all(dir).with_context(|| format!("cannot create {}", dir.display()))?;
    write_png(&dir.join(format!("{stem}.png")), &img.map_channels(3, |v| crate::color::linear_to_srgb(v.clamp(0.0, 1.0))))?;
    write_exr(&dir.join(format!("{stem}.exr")), img)
}
