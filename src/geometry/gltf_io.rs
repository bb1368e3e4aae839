//! glTF 2.0 files (`.gltf` + `.bin`, or `.glb`): loading with the `gltf` crate, writing by hand.
//!
//! glTF puts v = 0 at the TOP of a texture; the Mesh uses the OBJ convention (v = 0 at the
//! bottom), so v ↦ 1 − v on load and on write.

use std::collections::HashMap;
use std::path::Path;
use std::sync::Arc;

use anyhow::{bail, Context, Result};
use glam::{Mat3, Mat4, Vec2, Vec3};
use serde_json::json;

use super::mesh::{Mesh, Part};
use super::obj::MaterialTextureNames;
use crate::color::srgb_to_linear;
use crate::image::safe_decode::guard;
use crate::image::Image;
use crate::material::{BaseColor, PartMaterial, Scalar};

/// A decoded glTF image as RGB. Colour images (`srgb`): 8/16-bit data is sRGB-encoded per the
/// spec and decoded to linear; data images (metallic-roughness) are linear as stored. Float data is
/// taken as linear either way.
fn decode_rgb(data: &gltf::image::Data, srgb: bool) -> Result<Image> {
    use gltf::image::Format::*;
    let (channels, bytes, is_float) = match data.format {
        R8 => (1, 1, false),
        R8G8 => (2, 1, false),
        R8G8B8 => (3, 1, false),
        R8G8B8A8 => (4, 1, false),
        R16 => (1, 2, false),
        R16G16 => (2, 2, false),
        R16G16B16 => (3, 2, false),
        R16G16B16A16 => (4, 2, false),
        R32G32B32FLOAT => (3, 4, true),
        R32G32B32A32FLOAT => (4, 4, true),
    };
    let (w, h) = (data.width as usize, data.height as usize);
    if data.pixels.len() != w * h * channels * bytes {
        bail!("image of {w}×{h} has {} bytes, expected {}", data.pixels.len(), w * h * channels * bytes);
    }
    let curve = |v: f32| if srgb { srgb_to_linear(v) } else { v };
    let value = |k: usize| -> f32 {
        let b = &data.pixels[k * bytes..(k + 1) * bytes];
        match (bytes, is_float) {
            (1, _) => curve(b[0] as f32 / 255.0),
            (2, _) => curve(u16::from_ne_bytes([b[0], b[1]]) as f32 / 65535.0),
            _ => f32::from_ne_bytes([b[0], b[1], b[2], b[3]]),
        }
    };
    let mut img = Image::new(w, h, 3);
    for p in 0..w * h {
        let base = p * channels;
        let rgb = if channels >= 3 { [value(base), value(base + 1), value(base + 2)] } else { [value(base); 3] };
        img.data[p * 3..p * 3 + 3].copy_from_slice(&rgb);
    }
    Ok(img)
}

fn material_from_gltf(m: &gltf::Material, images: &[gltf::image::Data], path: &Path) -> Result<PartMaterial> {
    let pbr = m.pbr_metallic_roughness();
    let factor = pbr.base_color_factor();
    let factor = Vec3::new(factor[0], factor[1], factor[2]);
    let name = m.name().map(str::to_string).unwrap_or_else(|| format!("material{}", m.index().unwrap_or(0)));
    let image = |info: gltf::texture::Info, srgb: bool| -> Result<Image> {
        let k = info.texture().source().index();
        let data = images.get(k).with_context(|| format!("{}: material {name}: image {k} missing", path.display()))?;
        decode_rgb(data, srgb).with_context(|| format!("{}: material {name}, image {k}", path.display()))
    };
    let base_color = match pbr.base_color_texture() {
        Some(info) => {
            let mut img = image(info, true)?;
            // The spec multiplies texture by factor; bake it in (the factor is linear).
            if factor != Vec3::ONE {
                for px in img.data.chunks_exact_mut(3) {
                    px[0] *= factor.x;
                    px[1] *= factor.y;
                    px[2] *= factor.z;
                }
            }
            BaseColor::Texture(Arc::new(img))
        }
        None => BaseColor::Constant(factor),
    };
    let (roughness, metallic) = match pbr.metallic_roughness_texture() {
        // The spec: roughness in green, metallic in blue, each times its factor.
        Some(info) => {
            let img = image(info, false)?;
            let channel = |c: usize, factor: f32| {
                let data = img.data.chunks_exact(3).map(|p| p[c] * factor).collect();
                Scalar::Texture(Arc::new(Image { width: img.width, height: img.height, channels: 1, data }))
            };
            (channel(1, pbr.roughness_factor()), channel(2, pbr.metallic_factor()))
        }
        None => (Scalar::Constant(pbr.roughness_factor()), Scalar::Constant(pbr.metallic_factor())),
    };
    Ok(PartMaterial { name, base_color, roughness, metallic })
}

struct Loader<'a> {
    path: &'a Path,
    buffers: &'a [gltf::buffer::Data],
    images: &'a [gltf::image::Data],
    mesh: Mesh,
    /// glTF material index (None = default material) → Mesh material index.
    material_map: HashMap<Option<usize>, usize>,
}

impl Loader<'_> {
    fn visit(&mut self, node: gltf::Node, parent: Mat4) -> Result<()> {
        let transform = parent * Mat4::from_cols_array_2d(&node.transform().matrix());
        if let Some(m) = node.mesh() {
            for prim in m.primitives() {
                self.add_primitive(&m, &prim, transform)?;
            }
        }
        for child in node.children() {
            self.visit(child, transform)?;
        }
        Ok(())
    }

    fn add_primitive(&mut self, m: &gltf::Mesh, prim: &gltf::Primitive, transform: Mat4) -> Result<()> {
        let mesh_name = m.name().map(str::to_string).unwrap_or_else(|| format!("mesh{}", m.index()));
        let ctx = || format!("{}: mesh {mesh_name}, primitive {}", self.path.display(), prim.index());
        if prim.mode() != gltf::mesh::Mode::Triangles {
            bail!("{}: only triangle lists are supported, found {:?}", ctx(), prim.mode());
        }
        let reader = prim.reader(|b| self.buffers.get(b.index()).map(|d| &d[..]));
        let positions: Vec<Vec3> =
            reader.read_positions().with_context(|| format!("{}: no POSITION", ctx()))?.map(Vec3::from_array).collect();
        let n = positions.len();
        let indices: Vec<u32> = match reader.read_indices() {
            Some(ix) => ix.into_u32().collect(),
            None => (0..n as u32).collect(),
        };
        if !indices.len().is_multiple_of(3) {
            bail!("{}: {} indices is not a multiple of 3", ctx(), indices.len());
        }
        if let Some(bad) = indices.iter().find(|&&i| i as usize >= n) {
            bail!("{}: index {bad} past {n} vertices", ctx());
        }
        // A mirroring transform flips the winding; swap two corners so faces keep their side.
        let mirror = transform.determinant() < 0.0;
        let local_tris: Vec<[u32; 3]> =
            indices.chunks_exact(3).map(|t| if mirror { [t[0], t[2], t[1]] } else { [t[0], t[1], t[2]] }).collect();
        let positions: Vec<Vec3> = positions.iter().map(|&p| transform.transform_point3(p)).collect();
        if let Some(k) = positions.iter().position(|p| !p.is_finite()) {
            bail!("{}: vertex {k}: position {} (after the node transforms) is not finite", ctx(), positions[k]);
        }
        let normal_matrix = Mat3::from_mat4(transform).inverse().transpose();
        let computed = Mesh::area_weighted_normals(&positions, &local_tris);
        let normals: Vec<Vec3> = match reader.read_normals() {
            Some(it) => it.zip(computed).map(|(nrm, c)| (normal_matrix * Vec3::from_array(nrm)).try_normalize().unwrap_or(c)).collect(),
            None => computed,
        };
        if normals.len() != n {
            bail!("{}: NORMAL has {} entries for {n} positions", ctx(), normals.len());
        }
        let uvs: Option<Vec<Vec2>> =
            reader.read_tex_coords(0).map(|t| t.into_f32().map(|[u, v]| Vec2::new(u, 1.0 - v)).collect());
        if uvs.as_ref().is_some_and(|u| u.len() != n) {
            bail!("{}: TEXCOORD_0 has a different count than POSITION", ctx());
        }
        if let Some((k, uv)) = uvs.iter().flatten().enumerate().find(|(_, t)| !t.is_finite()) {
            bail!("{}: vertex {k}: TEXCOORD_0 {uv} is not finite", ctx());
        }

        let key = prim.material().index();
        let material = match self.material_map.get(&key) {
            Some(&k) => k,
            None => {
                let mat = match key {
                    Some(_) => material_from_gltf(&prim.material(), self.images, self.path)?,
                    None => PartMaterial {
                        name: "default".into(),
                        base_color: BaseColor::Constant(Vec3::ONE), // glTF's default material
                        roughness: Scalar::Constant(1.0),
                        metallic: Scalar::Constant(1.0),
                    },
                };
                self.mesh.materials.push(mat);
                self.material_map.insert(key, self.mesh.materials.len() - 1);
                self.mesh.materials.len() - 1
            }
        };
        let name = if m.primitives().len() > 1 { format!("{mesh_name}.{}", prim.index()) } else { mesh_name };
        let base = self.mesh.positions.len() as u32;
        let part = self.mesh.parts.len() as u32;
        self.mesh.parts.push(Part { name, material, has_uv: uvs.is_some() });
        self.mesh.positions.extend(positions);
        self.mesh.normals.extend(normals);
        self.mesh.uvs.extend(uvs.unwrap_or_else(|| vec![Vec2::ZERO; n]));
        self.mesh.triangles.extend(local_tris.iter().map(|t| t.map(|i| i + base)));
        self.mesh.triangle_part.extend(std::iter::repeat_n(part, local_tris.len()));
        Ok(())
    }
}

/// Load a `.gltf` or `.glb` file: every triangle primitive of the default scene (node transforms
/// applied; normals by the inverse transpose) becomes a part. Materials: baseColorFactor
/// (× baseColorTexture, sRGB-decoded and baked), roughnessFactor and metallicFactor (× the green and
/// blue channels of metallicRoughnessTexture, linear, baked).
/// Not read: normal/occlusion/emissive maps, texCoord sets other than 0.
pub fn load_gltf(path: impl AsRef<Path>) -> Result<Mesh> {
    let path = path.as_ref();
    // The gltf crate indexes accessors and buffers as the file says; a corrupt file may panic inside it.
    guard(path, "glTF file", || load_gltf_unguarded(path))
}

fn load_gltf_unguarded(path: &Path) -> Result<Mesh> {
    let (doc, buffers, images) = gltf::import(path).with_context(|| format!("reading glTF file {}", path.display()))?;
    let mut loader = Loader { path, buffers: &buffers, images: &images, mesh: Mesh::default(), material_map: HashMap::new() };
    match doc.default_scene().or_else(|| doc.scenes().next()) {
        Some(scene) => {
            for node in scene.nodes() {
                loader.visit(node, Mat4::IDENTITY)?;
            }
        }
        // No scene: the meshes as they are.
        None => {
            for m in doc.meshes() {
                for prim in m.primitives() {
                    loader.add_primitive(&m, &prim, Mat4::IDENTITY)?;
                }
            }
        }
    }
    if loader.mesh.triangles.is_empty() {
        bail!("glTF file {} contains no triangles", path.display());
    }
    Ok(loader.mesh)
}

/// Appends little-endian f32/u32 data to the binary buffer and records a bufferView + accessor.
struct BinWriter {
    bin: Vec<u8>,
    views: Vec<serde_json::Value>,
    accessors: Vec<serde_json::Value>,
}

impl BinWriter {
    fn push(&mut self, bytes: Vec<u8>, count: usize, kind: &str, component: u32, target: u32, extra: serde_json::Value) -> usize {
        while !self.bin.len().is_multiple_of(4) {
            self.bin.push(0);
        }
        self.views.push(json!({ "buffer": 0, "byteOffset": self.bin.len(), "byteLength": bytes.len(), "target": target }));
        self.bin.extend(bytes);
        let mut acc = json!({ "bufferView": self.views.len() - 1, "componentType": component, "count": count, "type": kind });
        if let (Some(a), Some(e)) = (acc.as_object_mut(), extra.as_object()) {
            a.extend(e.clone());
        }
        self.accessors.push(acc);
        self.accessors.len() - 1
    }
}

const FLOAT: u32 = 5126;
const UNSIGNED_INT: u32 = 5125;
const ARRAY_BUFFER: u32 = 34962;
const ELEMENT_ARRAY_BUFFER: u32 = 34963;

fn f32_bytes(values: impl Iterator<Item = f32>) -> Vec<u8> {
    values.flat_map(f32::to_le_bytes).collect()
}

/// Write `mesh` as glTF 2.0: `.glb` (one binary file) if the extension is `glb`, else `.gltf`
/// with a `.bin` beside it. One primitive per part with its own vertices (so a reload gives the
/// same parts); materials as pbrMetallicRoughness factors, double-sided; `textures[i]` optionally
/// names material `i`'s images (written by the caller, relative URIs): base colour (sRGB), the
/// packed occlusion-roughness-metallic image and the normal map (the OBJ-only single-channel
/// roughness and metallic names are not used).
pub fn write_gltf(path: impl AsRef<Path>, mesh: &Mesh, textures: &[MaterialTextureNames]) -> Result<()> {
    let path = path.as_ref();
    mesh.validate().map_err(|e| anyhow::anyhow!("cannot write {}: invalid mesh: {e}", path.display()))?;
    let glb = path.extension().is_some_and(|e| e.eq_ignore_ascii_case("glb"));
    let mut w = BinWriter { bin: Vec::new(), views: Vec::new(), accessors: Vec::new() };

    let mut by_part: Vec<Vec<usize>> = vec![Vec::new(); mesh.parts.len()];
    for (t, &p) in mesh.triangle_part.iter().enumerate() {
        by_part[p as usize].push(t);
    }
    let mut primitives = Vec::new();
    for (part, tris) in mesh.parts.iter().zip(&by_part) {
        if tris.is_empty() {
            continue;
        }
        // The part's vertices in order of first use.
        let mut local: HashMap<u32, u32> = HashMap::new();
        let mut order: Vec<usize> = Vec::new();
        let mut indices: Vec<u32> = Vec::with_capacity(tris.len() * 3);
        for &t in tris {
            for i in mesh.triangles[t] {
                let next = order.len() as u32;
                let k = *local.entry(i).or_insert_with(|| {
                    order.push(i as usize);
                    next
                });
                indices.push(k);
            }
        }
        let pos: Vec<Vec3> = order.iter().map(|&i| mesh.positions[i]).collect();
        let (lo, hi) = pos.iter().fold((pos[0], pos[0]), |(a, b), p| (a.min(*p), b.max(*p)));
        let n = order.len();
        let p_acc = w.push(
            f32_bytes(pos.iter().flat_map(|p| p.to_array())),
            n,
            "VEC3",
            FLOAT,
            ARRAY_BUFFER,
            json!({ "min": lo.to_array(), "max": hi.to_array() }),
        );
        let n_acc = w.push(f32_bytes(order.iter().flat_map(|&i| mesh.normals[i].to_array())), n, "VEC3", FLOAT, ARRAY_BUFFER, json!({}));
        let mut attributes = json!({ "POSITION": p_acc, "NORMAL": n_acc });
        if part.has_uv {
            let uv = f32_bytes(order.iter().flat_map(|&i| [mesh.uvs[i].x, 1.0 - mesh.uvs[i].y]));
            attributes["TEXCOORD_0"] = json!(w.push(uv, n, "VEC2", FLOAT, ARRAY_BUFFER, json!({})));
        }
        let i_acc = w.push(
            indices.iter().flat_map(|i| i.to_le_bytes()).collect(),
            indices.len(),
            "SCALAR",
            UNSIGNED_INT,
            ELEMENT_ARRAY_BUFFER,
            json!({}),
        );
        primitives.push((part.name.clone(), json!({ "attributes": attributes, "indices": i_acc, "material": part.material, "mode": 4 })));
    }

    let (mut images, mut gltf_textures, mut materials) = (Vec::new(), Vec::new(), Vec::new());
    for (i, m) in mesh.materials.iter().enumerate() {
        let factor = match &m.base_color {
            BaseColor::Constant(c) => *c,
            BaseColor::Texture(_) => Vec3::ONE,
        };
        let mut pbr = json!({
            "baseColorFactor": [factor.x, factor.y, factor.z, 1.0],
            "metallicFactor": m.metallic.mean(),
            "roughnessFactor": m.roughness.mean(),
        });
        let names = textures.get(i).cloned().unwrap_or_default();
        let mut texture = |uri: &String| {
            images.push(json!({ "uri": uri }));
            gltf_textures.push(json!({ "source": images.len() - 1 }));
            json!({ "index": gltf_textures.len() - 1 })
        };
        if let Some(uri) = &names.base_color {
            pbr["baseColorTexture"] = texture(uri);
        }
        if let Some(uri) = &names.occlusion_roughness_metallic {
            // The factors multiply the image: 1 leaves the texels as they are.
            pbr["metallicRoughnessTexture"] = texture(uri);
            pbr["metallicFactor"] = json!(1.0);
            pbr["roughnessFactor"] = json!(1.0);
        }
        let mut material = json!({ "name": m.name, "pbrMetallicRoughness": pbr, "doubleSided": true });
        if let Some(uri) = &names.normal {
            material["normalTexture"] = texture(uri);
        }
        materials.push(material);
    }

    // One glTF mesh per part keeps part names (glTF names meshes, not primitives).
    let meshes: Vec<_> = primitives.iter().map(|(name, p)| json!({ "name": name, "primitives": [p] })).collect();
    let nodes: Vec<_> = (0..meshes.len()).map(|k| json!({ "mesh": k })).collect();
    while !w.bin.len().is_multiple_of(4) {
        w.bin.push(0);
    }
    let bin_name = path.with_extension("bin");
    let mut buffer = json!({ "byteLength": w.bin.len() });
    if !glb {
        let name = bin_name.file_name().and_then(|n| n.to_str()).context("buffer file name is not UTF-8")?;
        buffer["uri"] = json!(name);
    }
    let mut doc = json!({
        "asset": { "version": "2.0", "generator": "reconstruct" },
        "scene": 0,
        "scenes": [{ "nodes": (0..nodes.len()).collect::<Vec<_>>() }],
        "nodes": nodes,
        "meshes": meshes,
        "materials": materials,
        "buffers": [buffer],
        "bufferViews": w.views,
        "accessors": w.accessors,
    });
    if !images.is_empty() {
        doc["images"] = json!(images);
        doc["textures"] = json!(gltf_textures);
    }
    let text = serde_json::to_string(&doc)?;
    if glb {
        let mut json_chunk = text.into_bytes();
        while !json_chunk.len().is_multiple_of(4) {
            json_chunk.push(b' ');
        }
        let total = 12 + 8 + json_chunk.len() + 8 + w.bin.len();
        let mut out = Vec::with_capacity(total);
        out.extend(b"glTF");
        out.extend(2u32.to_le_bytes());
        out.extend((total as u32).to_le_bytes());
        out.extend((json_chunk.len() as u32).to_le_bytes());
        out.extend(b"JSON");
        out.extend(json_chunk);
        out.extend((w.bin.len() as u32).to_le_bytes());
        out.extend(b"BIN\0");
        out.extend(&w.bin);
        std::fs::write(path, out).with_context(|| format!("writing {}", path.display()))
    } else {
        std::fs::write(&bin_name, &w.bin).with_context(|| format!("writing {}", bin_name.display()))?;
        std::fs::write(path, text).with_context(|| format!("writing {}", path.display()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::primitives::MeshBuilder;

    #[test]
    fn metallic_roughness_texture_gives_linear_roughness_and_metallic_textures() {
        let dir = std::env::temp_dir().join(format!("reconstruct-gltf-orm-{}", std::process::id()));
        std::fs::create_dir_all(&dir).expect("test setup");
        let mut b = MeshBuilder::new();
        let part = b.part(PartMaterial::constant("m", Vec3::ONE, 0.5, 0.0));
        b.cylinder(part, Vec2::ZERO, 1.0, 0.0, 1.0, 8);
        let path = dir.join("orm.gltf");
        write_gltf(&path, &b.build(), &[]).expect("test setup");
        // Add a metallicRoughness texture (codes: green = roughness, blue = metallic) with factors.
        let codes: Vec<u8> = (0..4u8).flat_map(|i| [7, 40 + 50 * i, 250 - 60 * i]).collect();
        image::RgbImage::from_raw(2, 2, codes.clone()).expect("test setup").save(dir.join("orm.png")).expect("test setup");
        let mut doc: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&path).expect("written")).expect("json");
        doc["images"] = json!([{ "uri": "orm.png" }]);
        doc["textures"] = json!([{ "source": 0 }]);
        let pbr = &mut doc["materials"][0]["pbrMetallicRoughness"];
        pbr["metallicRoughnessTexture"] = json!({ "index": 0 });
        pbr["roughnessFactor"] = json!(0.5);
        pbr["metallicFactor"] = json!(1.0);
        std::fs::write(&path, doc.to_string()).expect("test setup");

        let mesh = load_gltf(&path).expect("loads");
        let m = &mesh.materials[0];
        let (Scalar::Texture(r), Scalar::Texture(k)) = (&m.roughness, &m.metallic) else { panic!("not textured: {m:?}") };
        for (i, px) in codes.chunks_exact(3).enumerate() {
            assert!((r.data[i] - 0.5 * px[1] as f32 / 255.0).abs() < 1e-6, "roughness texel {i}");
            assert!((k.data[i] - px[2] as f32 / 255.0).abs() < 1e-6, "metallic texel {i}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
