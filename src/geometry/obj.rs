//! Wavefront OBJ/MTL files: loading (tobj), with or without the MTL materials, and writing meshes
//! back out for exports.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::path::Path;

use anyhow::{bail, Context, Result};
use glam::{Vec2, Vec3};

use super::mesh::{Mesh, Part};
use super::texture_file::TextureCache;
use crate::image::safe_decode::guard;
use crate::material::{BaseColor, PartMaterial, Scalar};

/// Material of parts whose file names none (Blender's default grey, fairly rough dielectric).
fn default_material(name: &str) -> PartMaterial {
    PartMaterial { name: name.to_string(), base_color: BaseColor::Constant(Vec3::splat(0.8)), roughness: Scalar::Constant(0.5), metallic: Scalar::Constant(0.0) }
}

/// Blender's OBJ exporter writes Ns = (1 − roughness)²·1000; invert it.
pub fn roughness_from_ns(ns: f32) -> f32 {
    1.0 - (ns.clamp(0.0, 1000.0) / 1000.0).sqrt()
}

/// The inverse of [`roughness_from_ns`].
pub fn ns_from_roughness(roughness: f32) -> f32 {
    let s = 1.0 - roughness.clamp(0.0, 1.0);
    s * s * 1000.0
}

/// Geometry of an OBJ file: the mesh (materials left empty) and, per part, the MTL material
/// index tobj reported.
struct ObjGeometry {
    mesh: Mesh,
    part_mtl: Vec<Option<usize>>,
    mtl: Vec<tobj::Material>,
}

fn read_obj_geometry(path: &Path) -> Result<ObjGeometry> {
    let options = tobj::LoadOptions { single_index: true, triangulate: true, ignore_points: true, ignore_lines: true };
    let text = std::fs::read_to_string(path).with_context(|| format!("reading OBJ file {}", path.display()))?;
    let text = match repair_vt_numbered_like_v(&text) {
        Some(fixed) => {
            eprintln!(
                "note: {}: face texture indices repeat the vertex indices although some objects have no `vt`; \
                 re-indexed each object's `vt` block to its `v` block",
                path.display()
            );
            fixed
        }
        None => text,
    };
    let dir = path.parent().unwrap_or(Path::new(".")).to_path_buf();
    let (models, materials) = guard(path, "OBJ file", || {
        tobj::load_obj_buf(&mut std::io::BufReader::new(text.as_bytes()), &options, |mtl| tobj::load_mtl(dir.join(mtl)))
            .with_context(|| format!("reading OBJ file {}", path.display()))
    })?;
    // A missing or broken MTL is not fatal for geometry; parts fall back to the default material.
    let mtl = match materials {
        Ok(m) => m,
        Err(_) if models.iter().all(|m| m.mesh.material_id.is_none()) => Vec::new(),
        Err(e) => return Err(anyhow::anyhow!("{e}")).with_context(|| format!("reading the MTL file of {}", path.display())),
    };

    let mut mesh = Mesh::default();
    let mut part_mtl = Vec::new();
    let mut names_seen: HashMap<String, usize> = HashMap::new();
    for model in &models {
        let m = &model.mesh;
        if m.indices.is_empty() {
            continue;
        }
        let nv = m.positions.len() / 3;
        let base = mesh.positions.len() as u32;
        let part_index = mesh.parts.len() as u32;
        let positions: Vec<Vec3> = m.positions.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])).collect();
        let local_tris: Vec<[u32; 3]> = m.indices.chunks_exact(3).map(|t| [t[0], t[1], t[2]]).collect();
        if let Some(bad) = m.indices.iter().find(|&&i| i as usize >= nv) {
            bail!("OBJ file {}: object {} has a face index {} past its {} vertices", path.display(), model.name, bad, nv);
        }
        if let Some(k) = positions.iter().position(|p| !p.is_finite()) {
            bail!("OBJ file {}: object {}, vertex {k}: position {} is not finite", path.display(), model.name, positions[k]);
        }
        if let Some(k) = m.texcoords.chunks_exact(2).position(|t| !(t[0].is_finite() && t[1].is_finite())) {
            bail!("OBJ file {}: object {}, vertex {k}: texture coordinate {:?} is not finite", path.display(), model.name, &m.texcoords[2 * k..2 * k + 2]);
        }
        let normals: Vec<Vec3> = if m.normals.len() == m.positions.len() {
            // Normalise what the file gives; zero-length file normals fall back to face normals below.
            m.normals.chunks_exact(3).map(|n| Vec3::new(n[0], n[1], n[2]).normalize_or_zero()).collect()
        } else {
            Vec::new()
        };
        let computed = Mesh::area_weighted_normals(&positions, &local_tris);
        let normals: Vec<Vec3> = if normals.is_empty() {
            computed
        } else {
            normals.into_iter().zip(computed).map(|(n, c)| if n == Vec3::ZERO { c } else { n }).collect()
        };
        let has_uv = m.texcoords.len() / 2 == nv && nv > 0;
        let uvs: Vec<Vec2> =
            if has_uv { m.texcoords.chunks_exact(2).map(|t| Vec2::new(t[0], t[1])).collect() } else { vec![Vec2::ZERO; nv] };

        mesh.positions.extend(positions);
        mesh.normals.extend(normals);
        mesh.uvs.extend(uvs);
        mesh.triangles.extend(local_tris.iter().map(|t| [t[0] + base, t[1] + base, t[2] + base]));
        mesh.triangle_part.extend(std::iter::repeat_n(part_index, local_tris.len()));

        // tobj splits an object at every `usemtl`; keep part names unique.
        let count = names_seen.entry(model.name.clone()).or_insert(0);
        let name = if *count == 0 { model.name.clone() } else { format!("{}.{}", model.name, count) };
        *count += 1;
        mesh.parts.push(Part { name, material: 0, has_uv });
        part_mtl.push(m.material_id);
    }
    if mesh.triangles.is_empty() {
        bail!("OBJ file {} contains no faces", path.display());
    }
    Ok(ObjGeometry { mesh, part_mtl, mtl })
}

/// Some exporters (the hotdog's `gt/hotdog.obj` among them) write `f a/a/a` — texture index =
/// vertex index — while objects without UVs write no `vt` lines, so every later object's texture
/// indices point into the wrong `vt` block (or past the end). Each object's `vt` block is in the
/// order of its `v` block, so the right index is the vertex's offset within its object's `v` block
/// plus that object's first `vt`. Returns the re-indexed text when the file has exactly that shape:
/// fewer `vt` than `v`, every face corner's texture index equal to its vertex index, and every
/// object that faces take UVs from having as many `vt` as `v`. Otherwise `None` (file untouched).
fn repair_vt_numbered_like_v(text: &str) -> Option<String> {
    // (first v, v count, first vt, vt count) per object, 1-based global indices.
    let mut blocks: Vec<[usize; 4]> = vec![[1, 0, 1, 0]];
    let (mut nv, mut nvt) = (0usize, 0usize);
    let mut corners_with_vt = 0usize;
    for line in text.lines() {
        let mut w = line.split_whitespace();
        match w.next() {
            Some("o") => blocks.push([nv + 1, 0, nvt + 1, 0]),
            Some("v") => {
                nv += 1;
                blocks.last_mut()?[1] += 1;
            }
            Some("vt") => {
                nvt += 1;
                blocks.last_mut()?[3] += 1;
            }
            Some("f") => {
                for corner in w {
                    let mut it = corner.split('/');
                    let (v, vt) = (it.next()?, it.next().unwrap_or(""));
                    if vt.is_empty() {
                        continue;
                    }
                    if v != vt || v.starts_with('-') {
                        return None;
                    }
                    corners_with_vt += 1;
                }
            }
            _ => {}
        }
    }
    if corners_with_vt == 0 || nvt >= nv {
        return None;
    }
    let block_of = |v: usize| blocks.iter().rev().find(|b| b[1] > 0 && v >= b[0] && v < b[0] + b[1]);
    let mut out = String::with_capacity(text.len());
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("f ") {
            out.push('f');
            for corner in rest.split_whitespace() {
                let parts: Vec<&str> = corner.split('/').collect();
                out.push(' ');
                if parts.len() >= 2 && !parts[1].is_empty() {
                    let v: usize = parts[0].parse().ok()?;
                    let b = block_of(v)?;
                    if b[3] != b[1] {
                        return None;
                    }
                    let vt = b[2] + (v - b[0]);
                    out.push_str(&format!("{}/{}", parts[0], vt));
                    if parts.len() == 3 {
                        out.push('/');
                        out.push_str(parts[2]);
                    }
                } else {
                    out.push_str(corner);
                }
            }
            out.push('\n');
        } else {
            out.push_str(line);
            out.push('\n');
        }
    }
    Some(out)
}

fn parse_unknown(m: &tobj::Material, key: &str, path: &Path) -> Result<Option<f32>> {
    match m.unknown_param.get(key) {
        None => Ok(None),
        Some(s) => s
            .split_whitespace()
            .next()
            .and_then(|w| w.parse::<f32>().ok())
            .map(Some)
            .with_context(|| format!("MTL of {}: material {}: cannot parse `{key} {s}`", path.display(), m.name)),
    }
}

/// An MTL material as a PartMaterial. `textures` caches decoded files shared by several materials.
fn material_from_mtl(m: &tobj::Material, dir: &Path, obj_path: &Path, textures: &mut TextureCache) -> Result<PartMaterial> {
    let context = |key: &str| format!("{key} of material {} in the MTL of {}", m.name, obj_path.display());
    let constant_roughness = match parse_unknown(m, "Pr", obj_path)? {
        Some(r) => r,
        None => m.shininess.map(roughness_from_ns).unwrap_or(0.5),
    };
    // `map_Pr` / `map_Pm` (the PBR extension write_obj uses): linear single-value images.
    let scalar = |key: &str, constant: f32, textures: &mut TextureCache| -> Result<Scalar> {
        Ok(match m.unknown_param.get(key) {
            Some(file) => Scalar::Texture(textures.linear(&dir.join(file.trim()), 0).with_context(|| context(key))?),
            None => Scalar::Constant(constant.clamp(0.0, 1.0)),
        })
    };
    let roughness = scalar("map_Pr", constant_roughness, textures)?;
    let metallic = scalar("map_Pm", parse_unknown(m, "Pm", obj_path)?.unwrap_or(0.0), textures)?;
    let base_color = match &m.diffuse_texture {
        Some(file) => BaseColor::Texture(textures.srgb(&dir.join(file)).with_context(|| context("map_Kd"))?),
        None => BaseColor::Constant(m.diffuse.map(Vec3::from_array).unwrap_or(Vec3::splat(0.8))),
    };
    Ok(PartMaterial { name: m.name.clone(), base_color, roughness, metallic })
}

/// Load an OBJ file (and its MTL) as a Mesh: one part per object/group + material.
/// Materials: `Kd` = linear base colour, `map_Kd` = sRGB texture, roughness from `map_Pr` (linear
/// texture), else `Pr`, else `Ns` by Blender's rule; metallic from `map_Pm`, else `Pm`. Missing
/// normals are computed (area-weighted); parts without `vt` get zero UVs and `has_uv = false`.
pub fn load_obj(path: impl AsRef<Path>) -> Result<Mesh> {
    let path = path.as_ref();
    let ObjGeometry { mut mesh, part_mtl, mtl } = read_obj_geometry(path)?;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut textures = TextureCache::default();
    // Only materials that parts use, in order of first use.
    let mut mtl_to_material: HashMap<usize, usize> = HashMap::new();
    for (part, mtl_id) in mesh.parts.iter_mut().zip(part_mtl) {
        let key = mtl_id.filter(|&i| i < mtl.len());
        let next = mesh.materials.len();
        part.material = match key {
            Some(i) => match mtl_to_material.get(&i) {
                Some(&k) => k,
                None => {
                    mesh.materials.push(material_from_mtl(&mtl[i], dir, path, &mut textures)?);
                    mtl_to_material.insert(i, next);
                    next
                }
            },
            None => match mesh.materials.iter().position(|m| m.name == "default") {
                Some(k) => k,
                None => {
                    mesh.materials.push(default_material("default"));
                    next
                }
            },
        };
    }
    Ok(mesh)
}

/// An OBJ file's geometry with one part per object/group + material, and the name of each part's
/// MTL material (None without one); no material is read (`mesh.materials` is empty and every part
/// points at material 0: the caller supplies the materials, e.g. from a `materials.json`).
pub fn load_obj_geometry(path: impl AsRef<Path>) -> Result<(Mesh, Vec<Option<String>>)> {
    let ObjGeometry { mesh, part_mtl, mtl } = read_obj_geometry(path.as_ref())?;
    let names = part_mtl.iter().map(|k| k.and_then(|k| mtl.get(k)).map(|m| m.name.clone())).collect();
    Ok((mesh, names))
}

/// Texture file names an exported material refers to (the caller writes the images).
#[derive(Clone, Debug, Default)]
pub struct MaterialTextureNames {
    /// `map_Kd`: sRGB base-colour image.
    pub base_color: Option<String>,
    /// `map_Pr`: linear roughness image.
    pub roughness: Option<String>,
    /// `map_Pm`: linear metallic image.
    pub metallic: Option<String>,
    /// glTF only: the (occlusion, roughness, metallic) image, glTF's `metallicRoughnessTexture`
    /// layout (roughness in G, metallic in B), linear.
    pub occlusion_roughness_metallic: Option<String>,
    /// Tangent-space normal map in the MikkTSpace frame, +Y along +v (OBJ `map_Bump`, which
    /// Blender's importer reads as a normal map; glTF `normalTexture`), linear.
    pub normal: Option<String>,
}

/// Write `mesh` as an OBJ file with an MTL beside it (same stem, `.mtl`). `textures[i]` names the
/// texture files of material `i` (missing entries or `None` write constants only). Every vertex
/// gets `v`, `vt` and `vn` with the same index; faces of parts without UVs omit the `vt` index.
pub fn write_obj(path: impl AsRef<Path>, mesh: &Mesh, textures: &[MaterialTextureNames]) -> Result<()> {
    let path = path.as_ref();
    mesh.validate().map_err(|e| anyhow::anyhow!("cannot write {}: invalid mesh: {e}", path.display()))?;
    let mtl_path = path.with_extension("mtl");
    let mtl_name = mtl_path.file_name().and_then(|n| n.to_str()).context("MTL file name is not UTF-8")?.to_string();

    let mut mtl = String::from("# written by reconstruct: Kd linear base colour, Pr/Pm PBR roughness/metallic\n");
    for (i, m) in mesh.materials.iter().enumerate() {
        let names = textures.get(i).cloned().unwrap_or_default();
        let kd = match &m.base_color {
            BaseColor::Constant(c) => *c,
            BaseColor::Texture(_) => Vec3::ONE, // the map carries the colour
        };
        writeln!(mtl, "\nnewmtl {}", m.name)?;
        writeln!(mtl, "Ns {:.6}", ns_from_roughness(m.roughness.mean()))?;
        writeln!(mtl, "Kd {:.6} {:.6} {:.6}", kd.x, kd.y, kd.z)?;
        writeln!(mtl, "Ks 0.500000 0.500000 0.500000\nNi 1.450000\nd 1.000000\nillum 2")?;
        writeln!(mtl, "Pr {:.6}\nPm {:.6}", m.roughness.mean(), m.metallic.mean())?;
        if let Some(t) = &names.base_color {
            writeln!(mtl, "map_Kd {t}")?;
        }
        if let Some(t) = &names.roughness {
            writeln!(mtl, "map_Pr {t}")?;
        }
        if let Some(t) = &names.metallic {
            writeln!(mtl, "map_Pm {t}")?;
        }
        if let Some(t) = &names.normal {
            writeln!(mtl, "map_Bump {t}")?;
        }
    }
    std::fs::write(&mtl_path, mtl).with_context(|| format!("writing {}", mtl_path.display()))?;

    let mut obj = String::with_capacity(mesh.positions.len() * 100 + mesh.triangles.len() * 40);
    writeln!(obj, "# written by reconstruct\nmtllib {mtl_name}")?;
    for p in &mesh.positions {
        writeln!(obj, "v {} {} {}", p.x, p.y, p.z)?;
    }
    for t in &mesh.uvs {
        writeln!(obj, "vt {} {}", t.x, t.y)?;
    }
    for n in &mesh.normals {
        writeln!(obj, "vn {} {} {}", n.x, n.y, n.z)?;
    }
    // Group triangles by part, keeping their order within each part.
    let mut by_part: Vec<Vec<usize>> = vec![Vec::new(); mesh.parts.len()];
    for (t, &p) in mesh.triangle_part.iter().enumerate() {
        by_part[p as usize].push(t);
    }
    for (part, tris) in mesh.parts.iter().zip(&by_part) {
        if tris.is_empty() {
            continue;
        }
        writeln!(obj, "o {}\nusemtl {}", part.name, mesh.materials[part.material].name)?;
        for &t in tris {
            let [a, b, c] = mesh.triangles[t].map(|i| i + 1);
            if part.has_uv {
                writeln!(obj, "f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}")?;
            } else {
                writeln!(obj, "f {a}//{a} {b}//{b} {c}//{c}")?;
            }
        }
    }
    std::fs::write(path, obj).with_context(|| format!("writing {}", path.display()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use crate::geometry::texture_file::save_srgb_texture;
    use crate::image::Image;

    fn tmp_dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("reconstruct-obj-{tag}-{}", std::process::id()));
        std::fs::create_dir_all(&d).expect("test setup");
        d
    }

    #[test]
    fn ns_rule_round_trips_and_matches_the_hotdog_mtl() {
        // hotdog.mtl: Salchicha Ns 250 ↔ roughness 0.5; Plate Ns 777.602985 ↔ 0.118182.
        assert!((roughness_from_ns(250.0) - 0.5).abs() < 1e-6);
        assert!((roughness_from_ns(777.602_97) - 0.118182).abs() < 1e-5);
        for r in [0.0, 0.08, 0.3, 0.9, 1.0] {
            assert!((roughness_from_ns(ns_from_roughness(r)) - r).abs() < 1e-5);
        }
    }

    #[test]
    fn mtl_materials_normals_and_missing_uvs() {
        let dir = tmp_dir("mtl");
        // A 2×2 texture, sRGB-encoded: codes 255 and 0 and 188 (≈ linear 0.5).
        let mut tex = Image::new(2, 2, 3);
        tex.data = vec![1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0, 0.5, 0.5, 0.5];
        save_srgb_texture(&dir.join("t.png"), &tex).expect("test setup");
        image::GrayImage::from_raw(2, 1, vec![51, 204]).expect("test setup").save(dir.join("m.png")).expect("test setup");
        std::fs::write(
            dir.join("m.mtl"),
            "newmtl A\nKd 0.2 0.4 0.6\nNs 250\nPm 0.25\nnewmtl B\nKd 1 1 1\nPr 0.7\nmap_Kd t.png\nmap_Pm m.png\n",
        )
        .expect("test setup");
        // Part `a` has no vt and no vn; part `b` has both.
        std::fs::write(
            dir.join("m.obj"),
            "mtllib m.mtl\no a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 0\nusemtl A\nf 1 2 3\nf 2 4 3\n\
             o b\nv 0 0 1\nv 2 0 1\nv 0 2 1\nvt 0 0\nvt 1 0\nvt 0 1\nvn 0 0 -1\nusemtl B\nf 5/1/1 6/2/1 7/3/1\n",
        )
        .expect("test setup");
        let mesh = load_obj(dir.join("m.obj")).expect("test setup");
        mesh.validate().expect("test setup");
        assert_eq!(mesh.parts.len(), 2);
        assert_eq!(mesh.triangles.len(), 3);
        assert!(!mesh.parts[0].has_uv && mesh.parts[1].has_uv);
        // Computed normals of the flat z = 0 quad are +z (counter-clockwise faces).
        for t in 0..2 {
            for &i in &mesh.triangles[t] {
                assert!((mesh.normals[i as usize] - Vec3::Z).length() < 1e-6);
                assert_eq!(mesh.uvs[i as usize], Vec2::ZERO);
            }
        }
        let a = &mesh.materials[mesh.parts[0].material];
        assert!((a.roughness.constant().unwrap() - 0.5).abs() < 1e-6 && a.metallic.constant() == Some(0.25));
        assert!(matches!(a.base_color, BaseColor::Constant(c) if (c - Vec3::new(0.2, 0.4, 0.6)).length() < 1e-6));
        let b = &mesh.materials[mesh.parts[1].material];
        assert!((b.roughness.constant().unwrap() - 0.7).abs() < 1e-6);
        // map_Pm: a linear grey texture, codes 51 and 204 → 0.2 and 0.8 exactly as stored.
        let Scalar::Texture(m) = &b.metallic else { panic!("map_Pm not read: {:?}", b.metallic) };
        assert!((m.data[0] - 0.2).abs() < 1e-6 && (m.data[1] - 0.8).abs() < 1e-6, "{:?}", m.data);
        // Texel (1,1) (bottom right) is sRGB 188/255 → linear ≈ 0.5; vt v = 0 is the bottom row.
        let p = b.eval(Vec2::new(0.75, 0.25));
        assert!((p.kd - Vec3::splat(0.5)).abs().max_element() < 0.01, "{:?}", p.kd);
        let p = b.eval(Vec2::new(0.25, 0.75));
        assert!((p.kd - Vec3::X).abs().max_element() < 1e-5, "{:?}", p.kd);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn texture_indices_numbered_like_vertex_indices_are_repaired() {
        // Object a has no vt; object b's faces say 4/4 although its first vt is vt 1.
        let text = "o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1//1 2//2 3//3\n\
                    o b\nv 0 0 1\nv 1 0 1\nv 0 1 1\nvt 0.1 0.2\nvt 0.3 0.4\nvt 0.5 0.6\nf 4/4/4 5/5/5 6/6/6\n";
        let fixed = repair_vt_numbered_like_v(text).expect("test setup");
        assert!(fixed.contains("f 4/1/4 5/2/5 6/3/6"), "{fixed}");
        assert!(fixed.contains("f 1//1 2//2 3//3"));
        // A consistent file is left alone.
        let ok = "o b\nv 0 0 1\nv 1 0 1\nv 0 1 1\nvt 0 0\nvt 1 0\nvt 0 1\nf 1/1 2/2 3/3\n";
        assert!(repair_vt_numbered_like_v(ok).is_none());
        let dir = tmp_dir("vt");
        std::fs::write(dir.join("q.obj"), text).expect("test setup");
        let mesh = load_obj(dir.join("q.obj")).expect("test setup");
        assert!(!mesh.parts[0].has_uv && mesh.parts[1].has_uv);
        assert_eq!(mesh.uvs[mesh.triangles[1][0] as usize], Vec2::new(0.1, 0.2));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn non_finite_positions_and_uvs_are_refused_naming_the_file_and_vertex() {
        let dir = tmp_dir("nan");
        for (name, text, needle) in [
            ("p.obj", "o a\nv 0 0 0\nv 1 nan 0\nv 0 1 0\nf 1 2 3\n", "vertex 1: position"),
            ("i.obj", "o a\nv 0 0 0\nv 1 0 0\nv 0 1 inf\nf 1 2 3\n", "vertex 2: position"),
            ("t.obj", "o a\nv 0 0 0\nv 1 0 0\nv 0 1 0\nvt 0 0\nvt NaN 0\nvt 0 1\nf 1/1 2/2 3/3\n", "vertex 1: texture coordinate"),
        ] {
            std::fs::write(dir.join(name), text).expect("test setup");
            let msg = format!("{:#}", load_obj(dir.join(name)).unwrap_err());
            assert!(msg.contains(name) && msg.contains(needle) && msg.contains("not finite"), "{msg}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn missing_files_name_the_file() {
        let err = load_obj("/nonexistent/dir/x.obj").unwrap_err();
        assert!(format!("{err:#}").contains("/nonexistent/dir/x.obj"), "{err:#}");
    }
}
