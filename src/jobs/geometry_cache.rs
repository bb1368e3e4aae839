//! The geometry stage's result kept in the run folder (`geometry.json`), so that a rerun — after a
//! kill, or to extend the material fit — does not redo the visual hull and the geometry pass.
//! Only reconstructed geometry is kept (the ground-truth mesh is just loaded). The file records
//! the identity of what made it (the data, the scene spec, the geometry source and the pass
//! settings: [`GeometryKey`]); a file of another identity is ignored and replaced. It is written
//! atomically, after the pass: a kill during the pass leaves no file (or the previous run's), and
//! the rerun redoes the pass, which is deterministic for a given seed.
//!
//! The meshes are stored exactly (JSON numbers read back are the `f32`s written), so a run that
//! reuses the file trains on the very mesh an uninterrupted run had.

use std::path::Path;

use anyhow::{Context, Result};
use glam::{Vec2, Vec3};
use serde::{Deserialize, Serialize};

use crate::atomic_write;
use crate::fit::geometry_pass::GeometryPassConfig;
use crate::geometry::mesh::Part;
use crate::geometry::Mesh;
use crate::material::{BaseColor, PartMaterial, Scalar};
use crate::scene::dataset::Dataset;
use crate::scene::SceneSpec;

use super::geometry::{obtain_geometry, GeometryOutcome, GeometryReport, GeometrySource, HullRecord, PassLabels, PassRecord};
use super::run_identity::{DataIdentity, GeometryIdentity, PriorIdentity, SceneIdentity};

/// The file in the run folder.
pub const GEOMETRY_FILE: &str = "geometry.json";

/// What the geometry depends on (the first three parts of the run identity).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct GeometryKey {
    pub data: DataIdentity,
    pub scene: SceneIdentity,
    pub geometry: GeometryIdentity,
}

/// A mesh whose materials are constants, as plain arrays.
#[derive(Serialize, Deserialize)]
struct MeshRecord {
    positions: Vec<[f32; 3]>,
    normals: Vec<[f32; 3]>,
    uvs: Vec<[f32; 2]>,
    triangles: Vec<[u32; 3]>,
    triangle_part: Vec<u32>,
    /// (name, material, has_uv)
    parts: Vec<(String, usize, bool)>,
    /// (name, base colour, roughness, metallic)
    materials: Vec<(String, [f32; 3], f32, f32)>,
}

impl MeshRecord {
    /// `None` when a material has a texture (not kept: reconstructed meshes have constants).
    fn of(m: &Mesh) -> Option<MeshRecord> {
        let materials = m
            .materials
            .iter()
            .map(|pm| match (&pm.base_color, &pm.roughness, &pm.metallic) {
                (BaseColor::Constant(c), Scalar::Constant(r), Scalar::Constant(k)) => Some((pm.name.clone(), c.to_array(), *r, *k)),
                _ => None,
            })
            .collect::<Option<Vec<_>>>()?;
        Some(MeshRecord {
            positions: m.positions.iter().map(|p| p.to_array()).collect(),
            normals: m.normals.iter().map(|p| p.to_array()).collect(),
            uvs: m.uvs.iter().map(|p| p.to_array()).collect(),
            triangles: m.triangles.clone(),
            triangle_part: m.triangle_part.clone(),
            parts: m.parts.iter().map(|p| (p.name.clone(), p.material, p.has_uv)).collect(),
            materials,
        })
    }

    fn mesh(self) -> Mesh {
        Mesh {
            positions: self.positions.into_iter().map(Vec3::from_array).collect(),
            normals: self.normals.into_iter().map(Vec3::from_array).collect(),
            uvs: self.uvs.into_iter().map(Vec2::from_array).collect(),
            triangles: self.triangles,
            triangle_part: self.triangle_part,
            parts: self.parts.into_iter().map(|(name, material, has_uv)| Part { name, material, has_uv }).collect(),
            materials: self
                .materials
                .into_iter()
                .map(|(name, c, r, k)| PartMaterial { name, base_color: BaseColor::Constant(Vec3::from_array(c)), roughness: Scalar::Constant(r), metallic: Scalar::Constant(k) })
                .collect(),
        }
    }
}

#[derive(Serialize, Deserialize)]
struct Saved {
    key: GeometryKey,
    why: String,
    mesh: MeshRecord,
    vertex_kd: Option<Vec<[f32; 3]>>,
    hull: Option<MeshRecord>,
    hull_record: Option<HullRecord>,
    pass: Option<PassRecord>,
}

impl GeometryKey {
    pub fn of(spec: &SceneSpec, dataset: &Dataset, source: GeometrySource, pass: &GeometryPassConfig, prior: Option<&PriorIdentity>) -> Result<GeometryKey> {
        Ok(GeometryKey { data: DataIdentity::of(dataset)?, scene: SceneIdentity::of(spec), geometry: GeometryIdentity::of(spec, source, pass, prior)? })
    }
}

/// The saved outcome in `folder` when it was made with `key`.
fn load(folder: &Path, key: &GeometryKey) -> Option<GeometryOutcome> {
    let text = std::fs::read_to_string(folder.join(GEOMETRY_FILE)).ok()?;
    let saved: Saved = serde_json::from_str(&text).ok()?;
    if saved.key != *key {
        return None;
    }
    Some(GeometryOutcome {
        mesh: saved.mesh.mesh(),
        vertex_kd: saved.vertex_kd.map(|v| v.into_iter().map(Vec3::from_array).collect()),
        hull: saved.hull.map(MeshRecord::mesh),
        report: GeometryReport { used: key.geometry.source, why: saved.why, hull: saved.hull_record, pass: saved.pass, scores: None },
    })
}

fn save(folder: &Path, key: &GeometryKey, outcome: &GeometryOutcome) -> Result<()> {
    let (Some(mesh), hull) = (MeshRecord::of(&outcome.mesh), outcome.hull.as_ref().map(MeshRecord::of)) else { return Ok(()) };
    let hull = match hull {
        Some(None) => return Ok(()),
        Some(Some(h)) => Some(h),
        None => None,
    };
    let r = &outcome.report;
    let saved = Saved {
        key: key.clone(),
        why: r.why.clone(),
        mesh,
        vertex_kd: outcome.vertex_kd.as_ref().map(|v| v.iter().map(|c| c.to_array()).collect()),
        hull,
        hull_record: r.hull.clone(),
        pass: r.pass.clone(),
    };
    atomic_write::write(&folder.join(GEOMETRY_FILE), serde_json::to_string(&saved)?).with_context(|| format!("saving the geometry in {}", folder.display()))
}

/// The geometry of a run ([`obtain_geometry`]), reused from `folder` when it holds the result of
/// the same identity, else made and (when reconstructed) saved there. `labels` are the run's
/// prior (its identity and its labels) for the pass's normal prior.
pub fn obtain_or_reuse(folder: &Path, spec: &SceneSpec, dataset: &Dataset, source: GeometrySource, pass: &GeometryPassConfig, labels: Option<(&PriorIdentity, &PassLabels)>, progress: bool) -> Result<GeometryOutcome> {
    let key = GeometryKey::of(spec, dataset, source, pass, labels.map(|l| l.0))?;
    if key.geometry.source != GeometrySource::Reconstruct {
        return obtain_geometry(spec, dataset, source, pass, None, progress);
    }
    if let Some(outcome) = load(folder, &key) {
        if progress {
            eprintln!("geometry: reusing the reconstruction saved in {}", folder.join(GEOMETRY_FILE).display());
        }
        return Ok(outcome);
    }
    let outcome = obtain_geometry(spec, dataset, source, pass, labels.map(|l| l.1), progress)?;
    save(folder, &key, &outcome)?;
    Ok(outcome)
}
