//! Isotropic remeshing of a closed triangle mesh toward a target edge length, by baby_shark's
//! incremental remesher: split long edges, collapse short ones, flip toward valence 6, smooth
//! tangentially, and project the vertices back onto the input surface. The visual hull uses it
//! to turn marching cubes' slivers into even triangles; the geometry pass uses it between its
//! stages to refine the mesh where the images can resolve more.
//!
//! The input must be manifold with one winding throughout (the remesher's corner table needs
//! it); the caller checks the output (`manifold::check_closed_manifold`), since the remesher's
//! own checks are local.

use anyhow::{bail, Result};
use baby_shark::exports::nalgebra::Vector3;
use baby_shark::mesh::corner_table::CornerTable;
use baby_shark::remeshing::incremental::IncrementalRemesher;
use glam::Vec3;

/// The remeshed positions and triangles. `iterations` rounds of split / collapse / flip / smooth;
/// `flips` false leaves edge flips out (the operation with the weakest topological test).
pub fn isotropic_remesh(positions: &[Vec3], triangles: &[[u32; 3]], target_edge: f32, iterations: u16, flips: bool) -> Result<(Vec<Vec3>, Vec<[u32; 3]>)> {
    if !(target_edge > 0.0 && target_edge.is_finite()) {
        bail!("remesh: the target edge length must be positive and finite (got {target_edge})");
    }
    let vertices: Vec<Vector3<f32>> = positions.iter().map(|p| Vector3::new(p.x, p.y, p.z)).collect();
    let faces: Vec<usize> = triangles.iter().flat_map(|t| t.map(|i| i as usize)).collect();
    let mut table = CornerTable::<f32>::from_vertex_and_face_slices(&vertices, &faces);
    if table.faces().next().is_none() {
        bail!("remesh: the surface ({} triangles) could not be loaded (not manifold)", triangles.len());
    }
    IncrementalRemesher::new().with_iterations_count(iterations).with_flip_edges(flips).remesh(&mut table, target_edge);
    let mut index = table.create_vertex_attribute::<u32>();
    let mut out_positions = Vec::new();
    for v in table.vertices() {
        index[v] = out_positions.len() as u32;
        let p = table.vertex_position(v);
        out_positions.push(Vec3::new(p.x, p.y, p.z));
    }
    let out_triangles = table
        .faces()
        .map(|f| {
            let (a, b, c) = table.face_vertices(f);
            [index[a], index[b], index[c]]
        })
        .collect();
    Ok((out_positions, out_triangles))
}
