//! The surface of the solid a closed mesh encloses, extracted afresh: the repair of a mesh that has
//! folded through itself. An optimised mesh can push a sheet of its surface through another part of
//! itself (`inward_surface.rs` measures how much); every triangle is still fine locally, but the sheet
//! inside the object shades nothing right and the optimiser cannot pull it back out. What the mesh
//! encloses is still well defined, and its boundary is the surface the mesh should have been.
//!
//! **Inside.** A point is inside when the mesh winds around it a non-zero number of times (the
//! non-zero fill rule): a sheet pushed into the object (winding 2 where it overlaps) stays inside; a
//! thin part whose two sides have crossed (a plate's top pushed through its bottom: winding −1
//! between them) keeps its slab; a cavity, where an inner surface faces into it (winding 0), is
//! outside. The winding number at the grid points is counted along the grid's lines: one ray per
//! line and axis from beyond the mesh's box, every crossing signed by the way the triangle faces,
//! and each point summing the crossings ahead of it. A ray that runs exactly through a shared edge
//! can count a crossing twice or not at all, so the three axes vote, and the rays are moved off the
//! grid lines by a small fraction of a voxel (a mesh built on the grid, a box, would otherwise have
//! its edges on them). Why non-zero and not positive: on a folded hotdog mesh the folds are mostly
//! the plate's crossed sides (docs/geometry.md, *Folds through the surface*), which the positive
//! rule would cut out of the plate.
//!
//! **Field.** Marching cubes meshes the inside (−1) and outside (+1) after a 3×3×3 box filter. The
//! filter is what makes the result usable: where two sheets of a fold cross, what lies between them
//! thins to nothing, and marching cubes on the raw inside/outside, or on it signed with the exact
//! distance to the mesh, leaves there slivers and zero-area triangles that the remesher cannot mend
//! (on a folded hotdog mesh, 191–776 degenerate triangles after the remesh; 0 after the filter). The
//! price: the level set passes midway between the inside and outside points, within about a voxel
//! of the boundary (refunded below), and a part thinner than two voxels is lost. The geometry pass
//! samples at half its next stage's edge, so that is a part thinner than one triangle edge.
//!
//! **Surface.** The level set is meshed closed and manifold and its largest piece kept
//! (`iso_surface.rs`): cavities drop away. Marching cubes can leave an edge shared by four triangles
//! on some grids; the sheets are parted there, and should the surface still be broken the grid is
//! shifted by part of a voxel and sampled again (`GRID_SHIFTS`).
//!
//! **Back onto the mesh.** The boundary of what the mesh encloses is made of pieces of the mesh's
//! own triangles (those with the outside just in front and the inside just behind), so the level
//! set's offset need not be kept: each of its vertices moves to its closest point on those triangles
//! when that lies within a voxel and faces the same way (`snap_to_surface`). Parts thinner than two
//! voxels stay lost: the grid never saw them inside.

use anyhow::{bail, Context, Result};
use glam::Vec3;
use rayon::prelude::*;

use super::bvh::Bvh;
use super::closest_point::SurfaceQuery;
use super::iso_surface::{closed_level_surface, FieldGrid, LevelSurface};
use super::Mesh;

/// Grid points at most (256³): the grid holds a value per point (64 MiB) and marching cubes visits
/// each; a finer voxel than asked is coarsened to stay within it (`EnclosedSurface::voxel`).
pub const MAX_GRID_POINTS: usize = 1 << 24;

/// Shifts of the grid's origin, in voxels along the diagonal, tried in turn until marching cubes
/// gives a clean surface: irrational shares, so that no two grids share points.
const GRID_SHIFTS: [f32; 3] = [0.0, 0.381_966, 0.723_607];

/// Crossings followed along one grid line before the rest of the line is given up (counted as
/// outside): far more than any mesh meant to be traced folds over itself.
const MAX_CROSSINGS: usize = 1024;

/// The surface extracted, in the input mesh's parts and materials (one part: the pass's meshes have
/// one), and how it was made.
pub struct EnclosedSurface {
    pub mesh: Mesh,
    /// The voxel used (the one asked, or coarser to stay within `MAX_GRID_POINTS`).
    pub voxel: f32,
    pub dims: [usize; 3],
    /// Grid points inside.
    pub inside_points: usize,
    /// Triangles marching cubes made before the largest piece was kept.
    pub marched: usize,
    /// Grids tried (`GRID_SHIFTS`), the last one giving the surface.
    pub attempts: usize,
    /// Vertices moved back onto the input mesh's surface (`snap_to_surface`).
    pub snapped: usize,
}

/// The boundary of what `mesh` (closed, possibly crossing itself) encloses, sampled at `voxel`.
pub fn enclosed_surface(mesh: &Mesh, voxel: f32) -> Result<EnclosedSurface> {
    if !(voxel > 0.0 && voxel.is_finite()) {
        bail!("enclosed surface: the voxel must be positive and finite (got {voxel})");
    }
    let (lo, hi) = mesh.bounds().context("enclosed surface: the mesh has no vertices")?;
    if !(lo.is_finite() && hi.is_finite()) {
        bail!("enclosed surface: the mesh has non-finite vertices");
    }
    // Two voxels of margin: the filter below reaches one voxel, and the outermost points must be
    // outside for the level set to close.
    const PAD: usize = 2;
    let size = hi - lo;
    let points = |h: f32| size.to_array().map(|s| (s / h).ceil() as usize + 1 + 2 * PAD);
    let mut h = voxel;
    while points(h).iter().product::<usize>() > MAX_GRID_POINTS {
        h *= 1.1;
    }
    let bvh = Bvh::build(mesh);
    // baby_shark's marching cubes leaves an edge shared by four triangles on some fields (seen on
    // folded hotdog meshes: one edge in some 200 000 triangles, and which edge depends on the last
    // bits of the input). iso_surface parts such sheets; should a surface still come out broken, the
    // same solid sampled on a grid shifted by part of a voxel is another draw of those last bits.
    let mut failures = Vec::new();
    for (attempt, shift) in GRID_SHIFTS.iter().enumerate() {
        let dims = points(h).map(|d| d + 1);
        let origin = lo - Vec3::splat((PAD as f32 + shift) * h);
        match sample_and_mesh(mesh, &bvh, origin, h, dims) {
            Ok((LevelSurface { positions, triangles, marched, .. }, inside_points)) => {
                let mut surface = mesh.with_geometry(positions, triangles);
                let snapped = snap_to_surface(&mut surface, mesh, &bvh, h)?;
                return Ok(EnclosedSurface { mesh: surface, voxel: h, dims, inside_points, marched, attempts: attempt + 1, snapped });
            }
            Err(e) => failures.push(format!("{e:#}")),
        }
    }
    bail!("enclosed surface: no grid of {} shifts gave a clean surface ({})", GRID_SHIFTS.len(), failures.join("; "))
}

/// The inside of `mesh` sampled on the grid at `origin`, `h`, `dims`, and its level set's surface,
/// with the number of grid points inside.
fn sample_and_mesh(mesh: &Mesh, bvh: &Bvh, origin: Vec3, h: f32, dims: [usize; 3]) -> Result<(LevelSurface, usize)> {
    let count = dims.iter().product::<usize>();

    // Votes of the three axes for each grid point being inside.
    let mut votes = vec![0u8; count];
    for axis in 0..3 {
        let (a1, a2) = ((axis + 1) % 3, (axis + 2) % 3);
        let lines: Vec<Vec<bool>> = (0..dims[a1] * dims[a2])
            .into_par_iter()
            .map(|line| {
                let (i1, i2) = (line % dims[a1], line / dims[a1]);
                line_inside(mesh, bvh, origin, h, dims[axis], axis, [(a1, i1), (a2, i2)])
            })
            .collect();
        for (line, inside) in lines.iter().enumerate() {
            let (i1, i2) = (line % dims[a1], line / dims[a1]);
            for (i, &v) in inside.iter().enumerate() {
                let mut c = [0usize; 3];
                c[axis] = i;
                c[a1] = i1;
                c[a2] = i2;
                votes[(c[2] * dims[1] + c[1]) * dims[0] + c[0]] += v as u8;
            }
        }
    }
    let inside: Vec<bool> = votes.iter().map(|&v| v >= 2).collect();
    let inside_points = inside.iter().filter(|&&v| v).count();
    if inside_points == 0 {
        bail!("the mesh encloses no grid point at voxel {h} (it is thinner than a voxel)");
    }

    // ±1 (inside negative), averaged over 3 points along each axis in turn: a 3×3×3 box filter,
    // whose values are odd multiples of 1/27 and so never 0. Beyond the grid is outside.
    let mut values: Vec<f32> = inside.iter().map(|&i| if i { -1.0 } else { 1.0 }).collect();
    for (axis, stride) in [1, dims[0], dims[0] * dims[1]].into_iter().enumerate() {
        let unfiltered = values.clone();
        values.par_iter_mut().enumerate().for_each(|(idx, v)| {
            let c = (idx / stride) % dims[axis];
            let before = if c > 0 { unfiltered[idx - stride] } else { 1.0 };
            let after = if c + 1 < dims[axis] { unfiltered[idx + stride] } else { 1.0 };
            *v = (before + unfiltered[idx] + after) / 3.0;
        });
    }
    values.iter_mut().for_each(|v| *v *= h);
    let grid = FieldGrid { origin, h, dims, values: &values };
    let surface = closed_level_surface(&grid, 2.0 * h)?;
    Ok((surface, inside_points))
}

/// The extracted surface's vertices moved back onto the input mesh's triangles that bound what it
/// encloses (`boundary_triangles`): each to its closest point there, when that point lies within
/// `reach` (one voxel) and its triangle faces within 60° of the extracted surface's normal at the
/// vertex. Returns how many moved.
///
/// Why: the boundary of what a mesh encloses is made of pieces of the mesh's own triangles, so away
/// from the lines where sheets cross, the exact surface is known; the filtered level set passes up
/// to about a voxel from it (half a voxel on flat parts, more where it rounds an edge). Moving each
/// vertex back refunds that price where the mesh can be trusted. A vertex whose closest point faces
/// another way (across a thin part, or at a crease where two sheets cross) stays where marching
/// cubes put it. A triangle the move would turn over or collapse (its normal no longer within 90°
/// of its unmoved one) has its vertices put back, until none is.
fn snap_to_surface(surface: &mut Mesh, mesh: &Mesh, bvh: &Bvh, reach: f32) -> Result<usize> {
    // Off the triangle by a thousandth of the reach; hits stepped over as along the grid's lines.
    let boundary = boundary_triangles(mesh, bvh, 1e-3 * reach, 1e-4 * reach);
    let bounding = mesh.with_geometry(mesh.positions.clone(), mesh.triangles.iter().zip(&boundary).filter(|(_, &b)| b).map(|(t, _)| *t).collect());
    if bounding.triangles.is_empty() {
        return Ok(0);
    }
    let query = SurfaceQuery::new(&bounding).context("enclosed surface: moving the vertices back onto the mesh")?;
    let min_cos = 0.5; // 60°: the crossing sheets of a fold meet at larger angles than the level set's own normals err.
    let before = surface.positions.clone();
    let mut moved: Vec<bool> = surface
        .positions
        .par_iter_mut()
        .zip(&surface.normals)
        .map(|(p, n)| match query.closest(*p) {
            Some(c) if c.distance <= reach && bounding.face_normal_scaled(c.triangle as usize).normalize_or_zero().dot(*n) >= min_cos => {
                *p = c.point;
                true
            }
            _ => false,
        })
        .collect();
    loop {
        let mut reverted = false;
        for &[a, b, c] in &surface.triangles {
            let [a, b, c] = [a as usize, b as usize, c as usize];
            if !(moved[a] || moved[b] || moved[c]) {
                continue;
            }
            let unmoved = (before[b] - before[a]).cross(before[c] - before[a]);
            let now = (surface.positions[b] - surface.positions[a]).cross(surface.positions[c] - surface.positions[a]);
            if now.dot(unmoved) <= 1e-3 * unmoved.length_squared() {
                for v in [a, b, c] {
                    surface.positions[v] = before[v];
                    reverted |= std::mem::replace(&mut moved[v], false);
                }
            }
        }
        if !reverted {
            break;
        }
    }
    surface.recompute_normals();
    Ok(moved.iter().filter(|&&m| m).count())
}

/// The mesh's surface crossings along the ray `start + t·dir`, in order, as (t, +1 where the ray
/// leaves the solid through a triangle facing along it / −1 where it enters); the winding number at
/// a point of the ray is the sum of the crossings beyond it. Each hit is stepped over by `step`.
fn crossings(mesh: &Mesh, bvh: &Bvh, start: Vec3, dir: Vec3, step: f32) -> Vec<(f32, i32)> {
    bvh.hits_along(start, dir, 0.0, step)
        .filter_map(|hit| {
            let facing = mesh.face_normal_scaled(hit.triangle as usize).dot(dir);
            (facing != 0.0).then_some((hit.t, if facing > 0.0 { 1i32 } else { -1 }))
        })
        .take(MAX_CROSSINGS)
        .collect()
}

/// Whether each triangle of `mesh` bounds what it encloses: the winding number is 0 just in front
/// of its centre and not 0 just behind it (`offset` away, counted along its normal each way). A
/// sheet pushed into the solid fails the first, one of two sheets lying on each other the second.
/// Crossings along the way are stepped over by `step`.
fn boundary_triangles(mesh: &Mesh, bvh: &Bvh, offset: f32, step: f32) -> Vec<bool> {
    (0..mesh.triangles.len())
        .into_par_iter()
        .map(|t| {
            let [a, b, c] = mesh.triangle_positions(t);
            let Some(n) = (b - a).cross(c - a).try_normalize() else { return false };
            let centre = (a + b + c) / 3.0;
            let winding = |side: f32| crossings(mesh, bvh, centre + side * offset * n, side * n, step).iter().map(|c| c.1).sum::<i32>();
            winding(1.0) == 0 && winding(-1.0) != 0
        })
        .collect()
}

/// Whether each grid point on one line along `axis` is inside (winding number ≠ 0). `fixed` holds
/// the other two axes and the line's index along each.
fn line_inside(mesh: &Mesh, bvh: &Bvh, origin: Vec3, h: f32, points: usize, axis: usize, fixed: [(usize, usize); 2]) -> Vec<bool> {
    let mut start = origin;
    // Off the grid line by an irrational share of a voxel in each of the other axes: parity changes
    // only across the surface, which lies much farther than this from nearly every grid point.
    for ((a, i), off) in fixed.into_iter().zip([0.000_618_034, 0.000_414_214]) {
        start[a] += h * (i as f32 + off);
    }
    start[axis] -= h;
    let mut dir = Vec3::ZERO;
    dir[axis] = 1.0;
    let crossings = crossings(mesh, bvh, start, dir, 1e-4 * h);
    // The winding number at t is the sum of the signed crossings beyond t.
    let mut inside = vec![false; points];
    let mut winding: i32 = crossings.iter().map(|c| c.1).sum();
    let mut next = 0;
    for (i, v) in inside.iter_mut().enumerate() {
        let t = h * (i as f32 + 1.0);
        while next < crossings.len() && crossings[next].0 < t {
            winding -= crossings[next].1;
            next += 1;
        }
        *v = winding != 0;
    }
    inside
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::icosphere::icosphere;
    use crate::geometry::inward_surface::inward_share;
    use crate::geometry::manifold::{check_closed_manifold, signed_volume};
    use std::f64::consts::PI;

    fn share(mesh: &Mesh) -> f64 {
        inward_share(mesh, &Bvh::build(mesh), 4000, 7).expect("the test meshes have area")
    }

    fn inverted(mut mesh: Mesh) -> Mesh {
        for t in mesh.triangles.iter_mut() {
            t.swap(1, 2);
        }
        mesh
    }

    /// Two unit spheres 1 apart, as one mesh crossing itself: the surface of their union comes out,
    /// closed and facing out, with the union's volume (2·(4/3)π − the lens, 5π/12).
    #[test]
    fn overlapping_spheres_give_the_surface_of_their_union() -> Result<()> {
        let mut mesh = icosphere(Vec3::ZERO, 1.0, 4);
        mesh.append(icosphere(Vec3::new(1.0, 0.0, 0.0), 1.0, 4));
        assert!(share(&mesh) > 0.2, "the crossing parts face into the other sphere: {}", share(&mesh));
        let out = enclosed_surface(&mesh, 0.04)?;
        check_closed_manifold(&out.mesh).map_err(anyhow::Error::msg)?;
        assert!(share(&out.mesh) < 0.005, "inward share after: {}", share(&out.mesh));
        let union = 2.0 * 4.0 / 3.0 * PI - 5.0 * PI / 12.0;
        // The icospheres are inscribed (volume 1.5 % below the spheres') and the grid adds its own.
        let v = signed_volume(&out.mesh);
        assert!((v / union - 1.0).abs() < 0.03, "volume {v} against the union's {union}");
        // Away from the circle where the spheres cross, the vertices sit on the input's triangles
        // again, not half a voxel off them.
        let query = SurfaceQuery::new(&mesh)?;
        let off: Vec<f32> = out.mesh.positions.iter().map(|&p| query.closest(p).map_or(f32::INFINITY, |c| c.distance)).collect();
        let on = off.iter().filter(|&&d| d < 1e-5).count() as f64 / off.len() as f64;
        assert!(on > 0.9 && out.snapped as f64 >= on * off.len() as f64, "{:.1} % of the vertices on the input surface ({} snapped)", 100.0 * on, out.snapped);
        let worst = off.iter().fold(0.0f32, |a, &b| a.max(b));
        assert!(worst < 0.04, "a vertex {worst} off the input surface");
        Ok(())
    }

    /// The triangles that bound the union of two crossing spheres are those outside the other
    /// sphere; a sheet inside the solid and a cavity's wall (facing into it) bound nothing.
    #[test]
    fn the_boundary_triangles_are_those_outside_the_other_sphere() {
        let centres = [Vec3::ZERO, Vec3::new(1.0, 0.0, 0.0)];
        let mut mesh = icosphere(centres[0], 1.0, 3);
        let first = mesh.triangles.len();
        mesh.append(icosphere(centres[1], 1.0, 3));
        let boundary = boundary_triangles(&mesh, &Bvh::build(&mesh), 1e-5, 1e-6);
        let mut judged = 0;
        for (t, &b) in boundary.iter().enumerate() {
            let other = centres[if t < first { 1 } else { 0 }];
            let inside = mesh.triangle_positions(t).map(|p| p.distance(other) < 1.0);
            // A triangle across the other sphere's surface is partly both.
            if inside.iter().all(|&i| i == inside[0]) {
                assert_eq!(b, !inside[0], "triangle {t}");
                judged += 1;
            }
        }
        assert!(judged * 10 > boundary.len() * 9, "only {judged} of {} triangles judged", boundary.len());

        let mut cavity = icosphere(Vec3::ZERO, 1.0, 2);
        let outer = cavity.triangles.len();
        cavity.append(inverted(icosphere(Vec3::ZERO, 0.5, 2)));
        cavity.append(icosphere(Vec3::new(0.0, 0.0, 0.7), 0.1, 1));
        let boundary = boundary_triangles(&cavity, &Bvh::build(&cavity), 1e-5, 1e-6);
        let inner = icosphere(Vec3::ZERO, 0.5, 2).triangles.len();
        assert!(boundary[..outer].iter().all(|&b| b), "the outer sphere bounds the solid");
        assert!(boundary[outer..outer + inner].iter().all(|&b| b), "the cavity's wall bounds the solid (outside just in front of it)");
        assert!(boundary[outer + inner..].iter().all(|&b| !b), "a sheet inside the solid bounds nothing");
    }

    /// A sheet (a sphere facing out) inside a sphere disappears; a sphere turned inside out inside
    /// one is a cavity, which is dropped; a mesh turned inside out is turned back.
    #[test]
    fn an_inner_sheet_and_a_cavity_are_removed_and_an_inverted_mesh_is_turned_back() -> Result<()> {
        let outer = icosphere(Vec3::ZERO, 1.0, 4);
        let exact = signed_volume(&outer);
        for inner in [icosphere(Vec3::new(0.1, 0.0, -0.1), 0.5, 3), inverted(icosphere(Vec3::new(0.1, 0.0, -0.1), 0.5, 3))] {
            let mut mesh = outer.clone();
            mesh.append(inner);
            let out = enclosed_surface(&mesh, 0.04)?;
            check_closed_manifold(&out.mesh).map_err(anyhow::Error::msg)?;
            let v = signed_volume(&out.mesh);
            assert!((v / exact - 1.0).abs() < 0.02, "volume {v} against the outer sphere's {exact}");
            let far_from_outer = out.mesh.positions.iter().map(|p| (p.length() - 1.0).abs()).fold(0.0f32, f32::max);
            assert!(far_from_outer < 0.04, "a vertex {far_from_outer} off the outer sphere");
        }
        // Turned inside out, the sphere still winds once (−1) around its inside: its surface comes out
        // facing outward.
        let out = enclosed_surface(&inverted(outer), 0.04)?;
        let v = signed_volume(&out.mesh);
        assert!((v / exact - 1.0).abs() < 0.02, "volume {v} against the outer sphere's {exact}");
        Ok(())
    }

    /// A box whose faces lie on the grid's lines is still read right (the rays are moved off them).
    #[test]
    fn a_box_on_the_grid_lines_keeps_its_volume() -> Result<()> {
        let corners: Vec<Vec3> = (0..8).map(|i| Vec3::new((i & 1) as f32, ((i >> 1) & 1) as f32, ((i >> 2) & 1) as f32) - 0.5).collect();
        // Two triangles per face, wound outward (corner bits: x 1, y 2, z 4).
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        let triangles = quads.iter().flat_map(|&[a, b, c, d]| [[a, b, c], [a, c, d]]).collect();
        let mesh = crate::geometry::iso_surface::grey_mesh("box", corners, triangles);
        assert!((signed_volume(&mesh) - 1.0).abs() < 1e-6, "the test box is wound outward");
        let h = 0.05;
        let out = enclosed_surface(&mesh, h)?;
        // The filter rounds the box's edges and corners over about a voxel: 12 edges of length 1 lose
        // up to (1 − π/4)·(2h)² each, 2.6 % at h = 0.05. A line of grid points read wrongly would
        // cut a groove through the box or leave a spike outside it.
        let v = signed_volume(&out.mesh);
        assert!(v < 1.0 && v > 1.0 - 12.0 * (1.0 - std::f64::consts::FRAC_PI_4) * (2.0 * h as f64).powi(2) - 0.01, "volume {v} against 1");
        let (lo, hi) = out.mesh.bounds().context("a surface")?;
        assert!(lo.cmpge(Vec3::splat(-0.5 - h)).all() && hi.cmple(Vec3::splat(0.5 + h)).all(), "bounds {lo}–{hi}");
        assert!(lo.cmple(Vec3::splat(-0.5 + h)).all() && hi.cmpge(Vec3::splat(0.5 - h)).all(), "bounds {lo}–{hi}");
        Ok(())
    }
}
