//! A ground-truth folder (a scene's `gt/`): which mesh file in it is the object, and the mesh with
//! its authoritative materials. The mesh is the one `mesh` names in `materials.json`, else the one
//! `.obj`, `.gltf` or `.glb` file in the folder, whatever its name; the materials are
//! `materials.json`'s when the folder has one, else the mesh file's own (MTL or glTF).

use std::path::{Path, PathBuf};

use anyhow::{bail, Context, Result};

use super::gltf_io::load_gltf;
use super::materials_json::{MaterialsJson, MATERIALS_JSON};
use super::mesh::Mesh;
use super::obj::{load_obj, load_obj_geometry};

/// File extensions of the mesh formats the loaders read.
pub const MESH_EXTENSIONS: [&str; 3] = ["obj", "gltf", "glb"];

fn is_mesh_file(path: &Path) -> bool {
    path.is_file() && path.extension().and_then(|e| e.to_str()).is_some_and(|e| MESH_EXTENSIONS.iter().any(|m| e.eq_ignore_ascii_case(m)))
}

fn is_obj(path: &Path) -> bool {
    path.extension().and_then(|e| e.to_str()).is_some_and(|e| e.eq_ignore_ascii_case("obj"))
}

/// The folder's `materials.json`, when it has one.
fn materials_json(gt_dir: &Path) -> Result<Option<MaterialsJson>> {
    let path = gt_dir.join(MATERIALS_JSON);
    path.is_file().then(|| MaterialsJson::load(&path)).transpose()
}

/// The mesh file of a ground-truth folder (reads only `materials.json` and the folder listing).
/// Errors name the folder when it is missing, holds no mesh, or holds several and
/// `materials.json` does not say which.
pub fn find_mesh_file(gt_dir: &Path) -> Result<PathBuf> {
    if !gt_dir.is_dir() {
        bail!("ground-truth folder {} not found", gt_dir.display());
    }
    if let Some(named) = materials_json(gt_dir)?.and_then(|m| m.mesh_file()) {
        if !is_mesh_file(&named) {
            bail!(
                "{} names mesh {}, which is not a {} file in that folder",
                gt_dir.join(MATERIALS_JSON).display(),
                named.display(),
                MESH_EXTENSIONS.map(|e| format!(".{e}")).join(" / ")
            );
        }
        return Ok(named);
    }
    let listing = std::fs::read_dir(gt_dir).with_context(|| format!("cannot list ground-truth folder {}", gt_dir.display()))?;
    let mut meshes: Vec<PathBuf> = listing.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| is_mesh_file(p)).collect();
    meshes.sort();
    match meshes.len() {
        1 => Ok(meshes.remove(0)),
        0 => bail!(
            "ground-truth folder {} holds no mesh: expected one .obj, .gltf or .glb file (or a \"mesh\" entry in its {MATERIALS_JSON})",
            gt_dir.display()
        ),
        _ => bail!(
            "ground-truth folder {} holds several meshes ({}): name the object's with \"mesh\": \"FILE\" in {}",
            gt_dir.display(),
            meshes.iter().filter_map(|p| p.file_name()).map(|n| n.to_string_lossy().into_owned()).collect::<Vec<_>>().join(", "),
            gt_dir.join(MATERIALS_JSON).display()
        ),
    }
}

/// Load a ground-truth folder's mesh with its materials (see the module doc).
pub fn load_ground_truth(gt_dir: impl AsRef<Path>) -> Result<Mesh> {
    let gt_dir = gt_dir.as_ref();
    let mesh_path = find_mesh_file(gt_dir)?;
    let Some(json) = materials_json(gt_dir)? else {
        return if is_obj(&mesh_path) { load_obj(&mesh_path) } else { load_gltf(&mesh_path) };
    };
    // materials.json decides the materials: an OBJ's MTL (and its textures) is not read at all.
    let (mut mesh, own_names) = if is_obj(&mesh_path) {
        load_obj_geometry(&mesh_path)?
    } else {
        let mesh = load_gltf(&mesh_path)?;
        let names = mesh.parts.iter().map(|p| Some(mesh.materials[p.material].name.clone())).collect();
        (mesh, names)
    };
    json.apply(&mut mesh, &own_names).with_context(|| format!("materials of {}", mesh_path.display()))?;
    mesh.validate().map_err(|e| anyhow::anyhow!("ground truth in {}: {e}", gt_dir.display()))?;
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp_dir(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("reconstruct-gt-{tag}-{}", std::process::id()));
        std::fs::remove_dir_all(&d).ok();
        std::fs::create_dir_all(&d).expect("test setup");
        d
    }

    const TRIANGLE: &str = "o tri\nv 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n";

    #[test]
    fn the_one_mesh_is_found_whatever_its_name() {
        let dir = tmp_dir("one");
        std::fs::write(dir.join("cow.obj"), TRIANGLE).expect("test setup");
        std::fs::write(dir.join("notes.txt"), "not a mesh").expect("test setup");
        assert_eq!(find_mesh_file(&dir).expect("one mesh"), dir.join("cow.obj"));
        let mesh = load_ground_truth(&dir).expect("loads with the default material");
        assert_eq!(mesh.triangles.len(), 1);
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn none_or_several_meshes_are_errors_naming_the_folder_unless_materials_json_says() {
        let dir = tmp_dir("several");
        let msg = format!("{:#}", find_mesh_file(&dir).unwrap_err());
        assert!(msg.contains("holds no mesh") && msg.contains(&dir.display().to_string()), "{msg}");
        std::fs::write(dir.join("a.obj"), TRIANGLE).expect("test setup");
        std::fs::write(dir.join("b.obj"), TRIANGLE).expect("test setup");
        let msg = format!("{:#}", find_mesh_file(&dir).unwrap_err());
        assert!(msg.contains("several meshes") && msg.contains("a.obj, b.obj"), "{msg}");
        let json = r#"{"mesh": "b.obj", "materials": {"tri": {"base_color": [0.1, 0.2, 0.3], "roughness": 0.25, "metallic": 1}}}"#;
        std::fs::write(dir.join(MATERIALS_JSON), json).expect("test setup");
        assert_eq!(find_mesh_file(&dir).expect("named"), dir.join("b.obj"));
        // No `parts` list: the part `tri` takes the material of the same name.
        let mesh = load_ground_truth(&dir).expect("loads");
        let m = &mesh.materials[mesh.parts[0].material];
        assert_eq!((m.name.as_str(), m.roughness.constant(), m.metallic.constant()), ("tri", Some(0.25), Some(1.0)));
        std::fs::write(dir.join(MATERIALS_JSON), json.replace("b.obj", "c.obj")).expect("test setup");
        let msg = format!("{:#}", find_mesh_file(&dir).unwrap_err());
        assert!(msg.contains("c.obj") && msg.contains(MATERIALS_JSON), "{msg}");
        assert!(format!("{:#}", find_mesh_file(&dir.join("nope")).unwrap_err()).contains("not found"));
        std::fs::remove_dir_all(&dir).ok();
    }

    #[test]
    fn bad_materials_are_reported_with_the_file_and_material() {
        let dir = tmp_dir("bad");
        std::fs::write(dir.join("m.obj"), TRIANGLE).expect("test setup");
        for (json, needle) in [
            (r#"{"materials": {"tri": {"base_color": [0.1, 0.2, 0.3], "roughness": 1.5, "metallic": 0}}}"#, "outside [0, 1]"),
            (r#"{"materials": {"tri": {"base_color": [0.1, 0.2, 0.3], "roughness": {"texture": "r.png", "colorspace": "sRGB"}, "metallic": 0}}}"#, "linear"),
            (r#"{"materials": {"tri": {"base_color": [0.1, 0.2, 0.3], "roughness": {"texture": "missing.png"}, "metallic": 0}}}"#, "missing.png"),
            (r#"{"materials": {"other": {"base_color": [0.1, 0.2, 0.3], "roughness": 0.5, "metallic": 0}}}"#, "part tri"),
            (r#"{"parts": [{"name": "ghost", "material": "x"}], "materials": {}}"#, "ghost"),
            (r#"{"materials": {"tri": {"base_color": "red", "roughness": 0.5, "metallic": 0}}}"#, "parsing"),
        ] {
            std::fs::write(dir.join(MATERIALS_JSON), json).expect("test setup");
            let msg = format!("{:#}", load_ground_truth(&dir).unwrap_err());
            assert!(msg.contains(needle) && msg.contains(MATERIALS_JSON), "{needle}: {msg}");
        }
        std::fs::remove_dir_all(&dir).ok();
    }
}
