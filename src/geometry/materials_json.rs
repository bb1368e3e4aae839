//! A ground-truth folder's `materials.json`: the authoritative materials of a scene's mesh (mesh
//! files' own MTL / glTF materials are often approximations of what the renderer used), which
//! part uses which, and optionally which mesh file in the folder it describes.
//!
//! ```json
//! { "mesh": "cow.obj",
//!   "parts": [ { "name": "Body", "material": "Hide" } ],
//!   "materials": { "Hide": { "base_color": { "texture": "hide.png", "colorspace": "sRGB" },
//!                            "roughness": { "texture": "hide_rough.png" },
//!                            "metallic": 0.0 } } }
//! ```
//! Base colour is linear RGB `[r, g, b]` or an sRGB-encoded texture; roughness and metallic are a
//! number in [0, 1] or a linear texture (`"channel"` 0–3 picks red/grey, green, blue or alpha;
//! default 0). Texture paths are relative to the folder. `mesh` and `parts` are optional: without
//! `parts`, each mesh part takes the material named like the part, else like its own (MTL / glTF)
//! material. Other keys (a renderer's extra BSDF settings, notes) are ignored. Format and rules:
//! docs/scene_files.md.

use std::collections::HashMap;
use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};
use glam::Vec3;
use serde::Deserialize;

use super::mesh::Mesh;
use super::texture_file::TextureCache;
use crate::material::{BaseColor, PartMaterial, Scalar};

/// The file name the ground-truth folder's materials go by.
pub const MATERIALS_JSON: &str = "materials.json";

#[derive(Deserialize)]
struct RawPart {
    name: String,
    material: String,
}

#[derive(Deserialize)]
#[serde(untagged)]
enum RawColour {
    Constant([f32; 3]),
    Texture { texture: String, colorspace: Option<String> },
}

#[derive(Deserialize)]
#[serde(untagged)]
enum RawScalar {
    Constant(f32),
    Texture { texture: String, colorspace: Option<String>, channel: Option<usize> },
}

#[derive(Deserialize)]
struct RawMaterial {
    base_color: RawColour,
    roughness: RawScalar,
    metallic: RawScalar,
}

#[derive(Deserialize)]
struct RawFile {
    mesh: Option<String>,
    parts: Option<Vec<RawPart>>,
    materials: HashMap<String, RawMaterial>,
}

/// A parsed `materials.json` (textures not read yet).
pub struct MaterialsJson {
    path: PathBuf,
    raw: RawFile,
}

impl MaterialsJson {
    /// Read and parse `path`.
    pub fn load(path: &Path) -> Result<MaterialsJson> {
        let text = std::fs::read_to_string(path).with_context(|| format!("reading {}", path.display()))?;
        let raw: RawFile = serde_json::from_str(&text).with_context(|| {
            format!(
                "parsing {}: expected {{\"materials\": {{NAME: {{\"base_color\", \"roughness\", \"metallic\"}}}}}} where each is a \
                 constant or {{\"texture\": FILE}}",
                path.display()
            )
        })?;
        Ok(MaterialsJson { path: path.to_path_buf(), raw })
    }

    /// The mesh file the JSON names, resolved against its folder.
    pub fn mesh_file(&self) -> Option<PathBuf> {
        self.raw.mesh.as_ref().map(|m| self.folder().join(m))
    }

    fn folder(&self) -> &Path {
        self.path.parent().unwrap_or(Path::new("."))
    }

    /// Replace `mesh`'s materials with the file's, part by part. `own_names[i]` is the name of part
    /// `i`'s own material in its mesh file (used when the JSON has no `parts` list).
    pub fn apply(&self, mesh: &mut Mesh, own_names: &[Option<String>]) -> Result<()> {
        let file = self.path.display();
        let material_of_part = |i: usize, part: &str| -> Result<String> {
            if let Some(parts) = &self.raw.parts {
                return parts
                    .iter()
                    .find(|p| p.name == part)
                    .map(|p| p.material.clone())
                    .with_context(|| format!("the mesh has part {part} that the `parts` list of {file} does not name"));
            }
            let own = own_names.get(i).cloned().flatten();
            [Some(part.to_string()), own.clone()]
                .into_iter()
                .flatten()
                .find(|n| self.raw.materials.contains_key(n))
                .with_context(|| {
                    format!(
                        "{file} has no `parts` list and no material named like mesh part {part}{}",
                        own.map(|o| format!(" or its material {o}")).unwrap_or_default()
                    )
                })
        };
        if let Some(parts) = &self.raw.parts {
            if let Some(p) = parts.iter().find(|p| !mesh.parts.iter().any(|q| q.name == p.name)) {
                bail!("{file} lists part {} that the mesh does not contain", p.name);
            }
        }
        // Materials in the order parts first use them; each texture file decoded once.
        let mut cache = TextureCache::default();
        let mut index_of: HashMap<String, usize> = HashMap::new();
        let mut materials = Vec::new();
        for (i, part) in mesh.parts.iter_mut().enumerate() {
            let name = material_of_part(i, &part.name)?;
            let index = match index_of.get(&name) {
                Some(&k) => k,
                None => {
                    let raw = self.raw.materials.get(&name).with_context(|| {
                        format!("{file}: part {} names material {name} which is not in `materials`", part.name)
                    })?;
                    let m = self.material(&name, raw, &mut cache).with_context(|| format!("{file}: material {name}"))?;
                    materials.push(m);
                    index_of.insert(name, materials.len() - 1);
                    materials.len() - 1
                }
            };
            part.material = index;
        }
        mesh.materials = materials;
        Ok(())
    }

    fn material(&self, name: &str, raw: &RawMaterial, cache: &mut TextureCache) -> Result<PartMaterial> {
        let dir = self.folder();
        let base_color = match &raw.base_color {
            RawColour::Constant(c) => {
                if c.iter().any(|v| !v.is_finite() || *v < 0.0) {
                    bail!("base_color {c:?} must be finite and ≥ 0 (linear RGB)");
                }
                BaseColor::Constant(Vec3::from_array(*c))
            }
            RawColour::Texture { texture, colorspace } => {
                if colorspace.as_deref().is_some_and(|c| !c.eq_ignore_ascii_case("srgb")) {
                    bail!("base_color texture {texture}: colour space {colorspace:?} is not supported (base-colour textures are sRGB)");
                }
                BaseColor::Texture(cache.srgb(&dir.join(texture))?)
            }
        };
        let scalar = |what: &str, raw: &RawScalar, cache: &mut TextureCache| -> Result<Scalar> {
            match raw {
                RawScalar::Constant(v) => {
                    if !(0.0..=1.0).contains(v) {
                        bail!("{what} {v} is outside [0, 1]");
                    }
                    Ok(Scalar::Constant(*v))
                }
                RawScalar::Texture { texture, colorspace, channel } => {
                    if colorspace.as_deref().is_some_and(|c| !["linear", "raw", "non-color"].iter().any(|l| c.eq_ignore_ascii_case(l))) {
                        bail!("{what} texture {texture}: colour space {colorspace:?} is not supported ({what} textures hold linear values)");
                    }
                    Ok(Scalar::Texture(cache.linear(&dir.join(texture), channel.unwrap_or(0))?))
                }
            }
        };
        let roughness = scalar("roughness", &raw.roughness, cache)?;
        let metallic = scalar("metallic", &raw.metallic, cache)?;
        Ok(PartMaterial { name: name.to_string(), base_color, roughness, metallic })
    }
}
