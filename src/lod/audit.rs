//! Checks of a frame's block list (SPEC section 7): the screen-space error audit and the
//! tiling check. Plain Rust, so that the guarantee is tested without a GPU.

use crate::lod::block::{block_vertex, cell_visible, BlockLayout, DrawBlock, Traversal};
use crate::lod::camera::Camera;
use crate::lod::geometry::interpolate;
use crate::lod::heightfield::{Heightfield, RawSamples};
use crate::lod::pyramid::MinMaxPyramid;
use glam::Vec3;

#[derive(Clone, Debug, Default, serde::Serialize)]
pub struct AuditResult {
    /// Largest pixel distance between a true sample and the rendered surface below it.
    pub max_error_px: f32,
    /// Samples inside the frustum that were checked.
    pub samples: u64,
    /// Visible samples that no drawn block covers (must be 0).
    pub uncovered: u64,
    /// Sample where the maximum was found.
    pub worst: (i64, i64),
}

/// Index of the drawn block over each finest-grid cell.
fn block_index_map(layout: &BlockLayout, blocks: &[DrawBlock]) -> Vec<u32> {
    let [cells, rows] = layout.cells();
    let mut map = vec![u32::MAX; cells * rows];
    for (i, b) in blocks.iter().enumerate() {
        let span = 1usize << b.lod;
        let (cx, cz) = (b.bx as usize * span, b.bz as usize * span);
        for z in cz..cz + span {
            map[z * cells + cx..z * cells + cx + span].fill(i as u32);
        }
    }
    map
}

/// Raw height of the rendered (stitched) block surface at integer sample `(x, z)`.
pub fn rendered_raw<S: RawSamples + ?Sized>(
    hf: &S,
    layout: &BlockLayout,
    b: &DrawBlock,
    x: i64,
    z: i64,
) -> Option<f32> {
    let k = layout.k() as i64;
    let stride = b.stride() as i64;
    let (ox, oz) = b.origin(layout);
    let (lx, lz) = (x - ox as i64, z - oz as i64);
    let qu = (lx / stride).min(k - 2);
    let qv = (lz / stride).min(k - 2);
    let cn = b.coarser;
    let touches =
        (qv == 0 && cn[0] > 0) || (qv == k - 2 && cn[2] > 0) || (qu == k - 2 && cn[1] > 0) || (qu == 0 && cn[3] > 0);
    // Collapsed edge vertices move by up to `ratio` quads along their edge.
    let reach = if touches { (*cn.iter().max().unwrap() as i64 / stride).min(k - 1) } else { 0 };
    for dv in -reach..=reach {
        for du in -reach..=reach {
            let (u, v) = (qu + du, qv + dv);
            if u < 0 || v < 0 || u > k - 2 || v > k - 2 {
                continue;
            }
            let vert = |uu: i64, vv: i64| block_vertex(hf, layout, b, uu as u32, vv as u32);
            let a = vert(u, v);
            let c = vert(u + 1, v);
            let i = vert(u + 1, v + 1);
            let g = vert(u, v + 1);
            for tri in [[a, c, i], [a, i, g]] {
                if let Some(h) = interpolate(&tri, x, z) {
                    return Some(h);
                }
            }
        }
    }
    None
}

/// For every sample inside the frustum, the pixel distance between the true point and
/// the rendered surface's point at the same `(x, z)`.
pub fn audit(hf: &Heightfield, layout: &BlockLayout, traversal: &Traversal, cam: &Camera) -> AuditResult {
    // The whole selection: an occluded block is still selected at its LOD, and the audit
    // does not rely on culling being right (the culling tests check that separately).
    let selection: Vec<DrawBlock> = traversal.selection().copied().collect();
    audit_blocks(hf, layout, &selection, cam)
}

/// [`audit`] of a block list as drawn (stitched), such as a streamed frame's.
pub fn audit_blocks(hf: &Heightfield, layout: &BlockLayout, selection: &[DrawBlock], cam: &Camera) -> AuditResult {
    let frustum = cam.frustum();
    let vp = cam.view_proj();
    let map = block_index_map(layout, selection);
    let [cells, rows] = layout.cells().map(|c| c as i64);
    let m = layout.m;
    let mut r = AuditResult::default();
    for z in 0..hf.height as i64 {
        for x in 0..hf.width as i64 {
            let raw = hf.raw_at(x, z);
            let p = hf.world_position(x, z, raw);
            if !frustum.contains_point(p) {
                continue;
            }
            r.samples += 1;
            // A sample on a cell boundary belongs to the cells on both sides: any drawn one
            // covers it (the other may be culled or in the margin).
            let mut idx = u32::MAX;
            'find: for cz in [z >> m, (z - 1).max(0) >> m] {
                for cx in [x >> m, (x - 1).max(0) >> m] {
                    let (cx, cz) = (cx.min(cells - 1), cz.min(rows - 1));
                    idx = map[(cz * cells + cx) as usize];
                    if idx != u32::MAX {
                        break 'find;
                    }
                }
            }
            if idx == u32::MAX {
                r.uncovered += 1;
                continue;
            }
            let err = rendered_error(hf, layout, &selection[idx as usize], cam, &vp, (x, z, p));
            if err > r.max_error_px {
                r.max_error_px = err;
                r.worst = (x, z);
            }
        }
    }
    r
}

/// Pixel distance between the true point `p` of a sample and block `b`'s rendered
/// surface at the same `(x, z)` (infinite where `b` does not cover it or either point
/// does not project).
fn rendered_error(
    hf: &Heightfield,
    layout: &BlockLayout,
    b: &DrawBlock,
    cam: &Camera,
    vp: &glam::Mat4,
    (x, z, p): (i64, i64, Vec3),
) -> f32 {
    match rendered_raw(hf, layout, b, x, z) {
        Some(rr) => {
            let q = Vec3::new(p.x, rr * hf.height_scale, p.z);
            match (cam.project(vp, p), cam.project(vp, q)) {
                (Some(a), Some(b)) => ((a.0 - b.0).powi(2) + (a.1 - b.1).powi(2)).sqrt(),
                _ => f32::INFINITY,
            }
        }
        None => f32::INFINITY,
    }
}

/// The audit of one block on its own: the largest pixel distance over its samples
/// (edges included) inside the frustum, whatever its neighbours draw.
pub fn audit_block(hf: &Heightfield, layout: &BlockLayout, b: &DrawBlock, cam: &Camera) -> f32 {
    let frustum = cam.frustum();
    let vp = cam.view_proj();
    let (ox, oz) = b.origin(layout);
    let size = layout.block_samples(b.lod) as i64;
    let mut worst = 0.0f32;
    for z in oz as i64..=(oz as i64 + size).min(hf.height as i64 - 1) {
        for x in ox as i64..=(ox as i64 + size).min(hf.width as i64 - 1) {
            let p = hf.world_position(x, z, hf.raw_at(x, z));
            if frustum.contains_point(p) {
                worst = worst.max(rendered_error(hf, layout, b, cam, &vp, (x, z, p)));
            }
        }
    }
    worst
}

/// Every visible finest-grid cell is covered by exactly one drawn block, and no cell by
/// two. Returns a description of the first failure.
pub fn check_tiling(
    hf: &Heightfield,
    mm: &MinMaxPyramid,
    layout: &BlockLayout,
    blocks: &[DrawBlock],
    cam: &Camera,
) -> Result<(), String> {
    let [cells, rows] = layout.cells();
    let mut count = vec![0u8; cells * rows];
    for b in blocks {
        let span = 1usize << b.lod;
        for z in b.bz as usize * span..(b.bz as usize + 1) * span {
            for x in b.bx as usize * span..(b.bx as usize + 1) * span {
                count[z * cells + x] += 1;
                if count[z * cells + x] > 1 {
                    return Err(format!("cell ({x}, {z}) is covered twice"));
                }
            }
        }
    }
    let frustum = cam.frustum();
    for z in 0..rows {
        for x in 0..cells {
            if count[z * cells + x] == 0 && cell_visible(hf, mm, layout, &frustum, x as u32, z as u32) {
                return Err(format!("visible cell ({x}, {z}) is not covered"));
            }
        }
    }
    Ok(())
}
