//! The closed surface where a field sampled on a regular grid crosses zero (negative inside): the
//! step shared by the visual hull (its field is the masks' cones) and the repair of a folded mesh
//! (its field is the filtered inside/outside of what the mesh encloses, `enclosed_surface.rs`).
//!
//! baby_shark's marching cubes 33 meshes the level set. It resolves the ambiguous cube
//! configurations, so the surface comes out closed (fast-surface-nets is faster but can join sheets
//! at a vertex, and the remesher that follows needs a manifold). What it still leaves is mended and
//! counted: where two sheets touch at a vertex or along an edge they are parted (a copy of the
//! vertex per sheet), only the largest connected piece is kept (specks, and cavities, which neither
//! caller wants), the few triangles wound against their neighbours are turned, and the whole is
//! turned to face outward. The result is checked to be a closed manifold.

use std::collections::HashMap;

use anyhow::{bail, Result};
use baby_shark::exports::nalgebra::Vector3;
use baby_shark::voxel::prelude::{MarchingCubesMesher, Volume};
use glam::{Vec2, Vec3};

use super::manifold::{check_closed_manifold, orient_consistently, split_pinched_vertices};
use super::{Mesh, Part};
use crate::material::{BaseColor, PartMaterial, Scalar};

/// Samples of a field on a regular grid, x fastest: point (i, j, k) is `origin + h·(i, j, k)`.
pub struct FieldGrid<'a> {
    pub origin: Vec3,
    pub h: f32,
    pub dims: [usize; 3],
    pub values: &'a [f32],
}

impl FieldGrid<'_> {
    pub fn index(&self, [i, j, k]: [usize; 3]) -> usize {
        (k * self.dims[1] + j) * self.dims[0] + i
    }
}

/// The level set's surface and what was mended on the way.
pub struct LevelSurface {
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
    /// Triangles marching cubes made, before the largest piece was kept.
    pub marched: usize,
    /// Vertices shared by two fans that were split.
    pub pinches: usize,
    /// Triangles turned to agree with their neighbours' winding.
    pub turned: usize,
}

/// The closed, outward-facing surface of `grid`'s zero level set. Grid points are read as far
/// outside (`outside`, which must exceed every value that matters) beyond the grid. Fails when the
/// level set is empty or the surface cannot be made a closed manifold.
pub fn closed_level_surface(grid: &FieldGrid, outside: f32) -> Result<LevelSurface> {
    let (mut positions, mut triangles) = marching_cubes(grid, outside);
    let marched = triangles.len();
    let pinches = split_pinched_vertices(&mut positions, &mut triangles);
    let (positions, mut triangles) = largest_component(&positions, &triangles);
    if triangles.is_empty() {
        bail!("the zero level set is empty (the shape is thinner than a voxel of {})", grid.h);
    }
    let turned = orient_consistently(&mut triangles).map_err(|e| anyhow::anyhow!("the marching-cubes surface is broken: {e}"))?;
    orient_outward(&positions, &mut triangles);
    check_closed_manifold(&grey_mesh("level set", positions.clone(), triangles.clone())).map_err(|e| anyhow::anyhow!("the marching-cubes surface is broken: {e}"))?;
    Ok(LevelSurface { positions, triangles, marched, pinches, turned })
}

/// A one-part mesh named `name`: grey, rough, dielectric, no UVs, normals from the triangles. The
/// shape every reconstruction starts as.
pub fn grey_mesh(name: &str, positions: Vec<Vec3>, triangles: Vec<[u32; 3]>) -> Mesh {
    let n = positions.len();
    let mut mesh = Mesh {
        normals: vec![Vec3::Z; n],
        uvs: vec![Vec2::ZERO; n],
        triangle_part: vec![0; triangles.len()],
        positions,
        triangles,
        parts: vec![Part { name: name.into(), material: 0, has_uv: false }],
        materials: vec![PartMaterial { name: name.into(), base_color: BaseColor::Constant(Vec3::splat(0.5)), roughness: Scalar::Constant(0.6), metallic: Scalar::Constant(0.0) }],
    };
    mesh.recompute_normals();
    mesh
}

/// Marching cubes 33 of the grid's zero level set, welded into indexed triangles in world units.
fn marching_cubes(grid: &FieldGrid, outside: f32) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let h = grid.h;
    let [nx, ny, nz] = grid.dims;
    let value_at = |p: &Vector3<f32>| -> f32 {
        let c = [p.x, p.y, p.z].map(|x| (x / h).round() as isize);
        if c.iter().zip(&grid.dims).any(|(&i, &n)| i < 0 || i >= n as isize) {
            return outside;
        }
        let v = grid.values[grid.index(c.map(|i| i as usize))];
        // A value within rounding of zero would put vertices of several cube edges on the same grid
        // point, which welding would then join into a pinch; keep every value a little off the level.
        let least = 1e-4 * h;
        if v.abs() < least {
            least.copysign(v)
        } else {
            v
        }
    };
    let extent = Vector3::new((nx - 1) as f32 * h, (ny - 1) as f32 * h, (nz - 1) as f32 * h);
    // baby_shark skips cubes with a corner outside its narrow band; keep every grid point in it.
    let band = (outside / h).ceil() as usize;
    let volume = Volume::from_fn(h, Vector3::zeros(), extent, band, value_at);
    let soup = MarchingCubesMesher::default().with_voxel_size(h).mesh(&volume);
    let mut index: HashMap<[u32; 3], u32> = HashMap::with_capacity(soup.len() / 2);
    let mut positions = Vec::new();
    let mut triangles = Vec::with_capacity(soup.len() / 3);
    for tri in soup.chunks_exact(3) {
        let ids = [0, 1, 2].map(|k| {
            let p = tri[k];
            *index.entry([p.x.to_bits(), p.y.to_bits(), p.z.to_bits()]).or_insert_with(|| {
                positions.push(grid.origin + Vec3::new(p.x, p.y, p.z));
                (positions.len() - 1) as u32
            })
        });
        if ids[0] != ids[1] && ids[1] != ids[2] && ids[0] != ids[2] {
            triangles.push(ids);
        }
    }
    (positions, triangles)
}
fn largest_component(positions: &[Vec3], triangles: &[[u32; 3]]) -> (Vec<Vec3>, Vec<[u32; 3]>) {
    let mut parent: Vec<u32> = (0..positions.len() as u32).collect();
    fn root(parent: &mut [u32], mut i: u32) -> u32 {
        while parent[i as usize] != i {
            parent[i as usize] = parent[parent[i as usize] as usize];
            i = parent[i as usize];
        }
        i
    }
    for t in triangles {
        let (a, b, c) = (root(&mut parent, t[0]), root(&mut parent, t[1]), root(&mut parent, t[2]));
        parent[b as usize] = a;
        let c = root(&mut parent, c);
        parent[c as usize] = a;
    }
    let mut counts: HashMap<u32, usize> = HashMap::new();
    for t in triangles {
        *counts.entry(root(&mut parent, t[0])).or_insert(0) += 1;
    }
    let Some((&best, _)) = counts.iter().max_by_key(|&(_, &c)| c) else {
        return (Vec::new(), Vec::new());
    };
    let mut remap = vec![u32::MAX; positions.len()];
    let mut kept_positions = Vec::new();
    let mut kept = Vec::new();
    for t in triangles {
        if root(&mut parent, t[0]) != best {
            continue;
        }
        kept.push(t.map(|i| {
            if remap[i as usize] == u32::MAX {
                remap[i as usize] = kept_positions.len() as u32;
                kept_positions.push(positions[i as usize]);
            }
            remap[i as usize]
        }));
    }
    (kept_positions, kept)
}

/// Reverses every triangle when the closed surface encloses negative volume.
fn orient_outward(positions: &[Vec3], triangles: &mut [[u32; 3]]) {
    let volume: f64 = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(|i| positions[i as usize].as_dvec3());
            a.dot(b.cross(c))
        })
        .sum();
    if volume < 0.0 {
        for t in triangles.iter_mut() {
            t.swap(1, 2);
        }
    }
}

