//! Which blocks a frame ray-casts instead of rasterizing (SPEC 10, seed 003).
//!
//! A ray-cast block is drawn by `raycast.vert`/`raycast.frag`: its bounding box, whose
//! pixels each cast a ray through the triangles the block's rasterized self would draw,
//! and write the hit's depth (deferred shading then shades it as any other pixel). The
//! shader intersects the block's own vertices and resolved corners along the a-i
//! diagonal; it does not morph or follow a coarser neighbour's edge, so only blocks that
//! do neither are eligible. Their error and their edges are then the rasterized block's.

use crate::lod::block::{BlockLayout, DrawBlock, MORPH_ONE};
use crate::lod::camera::Camera;
use crate::lod::heightfield::Heightfield;
use glam::{Vec2, Vec3};

/// Which blocks are ray-cast.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, clap::ValueEnum)]
pub enum Raycast {
    /// None: every block is rasterized.
    #[default]
    Off,
    /// Every other eligible block, as on a checkerboard: cast blocks beside drawn ones
    /// show any crack between the two.
    Checkerboard,
    /// Every eligible block (to measure the ray-caster's cost against the rasterizer's).
    All,
    /// Eligible blocks whose rays are estimated to cost less than the triangles they
    /// replace (measured costs of a ray a pixel against a triangle rasterized).
    Auto,
}

/// What a ray costs on the GPU, per pixel of the block's box, and what a rasterized
/// triangle costs: measured on lavapipe (2 cores) on ATLOD's turn path, every eligible
/// block ray-cast against none (docs/benchmarks.md, "Ray-cast blocks"). Fixed, not
/// calibrated at start-up: a GPU's ratio differs, and this one is what `auto` assumes.
pub const RAY_NS_PER_PIXEL: f64 = 271.0;
pub const RASTER_NS_PER_TRIANGLE: f64 = 106.0;

/// Raw height range of every block at every LOD (what a block's box needs), made once
/// per heightfield: level `j` has [`BlockLayout::blocks`]`(j)` blocks, row-major.
pub struct BlockRanges {
    levels: Vec<Vec<[f32; 2]>>,
}

impl BlockRanges {
    pub fn of(hf: &Heightfield, layout: &BlockLayout) -> Self {
        let [bx, bz] = layout.blocks(0);
        let side = layout.block_samples(0) as i64;
        let mut level0 = vec![[f32::INFINITY, f32::NEG_INFINITY]; bx * bz];
        for (i, r) in level0.iter_mut().enumerate() {
            let (x0, z0) = ((i % bx) as i64 * side, (i / bx) as i64 * side);
            for z in z0..=z0 + side {
                for x in x0..=x0 + side {
                    let v = hf.raw_at(x, z);
                    r[0] = r[0].min(v);
                    r[1] = r[1].max(v);
                }
            }
        }
        let mut levels = vec![level0];
        for j in 1..=layout.root_lod() {
            let [w, h] = layout.blocks(j);
            let prev = &levels[j as usize - 1];
            let pw = w * 2;
            let level = (0..w * h)
                .map(|i| {
                    let (a, b) = (i % w, i / w);
                    let mut r = [f32::INFINITY, f32::NEG_INFINITY];
                    for (dx, dz) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
                        let c = prev[(2 * b + dz) * pw + 2 * a + dx];
                        r = [r[0].min(c[0]), r[1].max(c[1])];
                    }
                    r
                })
                .collect();
            levels.push(level);
        }
        BlockRanges { levels }
    }

    /// The highest raw height of the terrain.
    pub fn top(&self) -> f32 {
        self.levels.last().map_or(f32::NEG_INFINITY, |l| l.iter().map(|r| r[1]).fold(f32::NEG_INFINITY, f32::max))
    }

    fn get(&self, layout: &BlockLayout, b: &DrawBlock) -> [f32; 2] {
        self.levels[b.lod as usize][b.bz as usize * layout.blocks(b.lod)[0] + b.bx as usize]
    }
}

/// A block's box in the camera's frame (min, max corners).
pub type WorldBox<'a> = Box<dyn Fn(&DrawBlock) -> (Vec3, Vec3) + 'a>;

/// Which blocks one frame ray-casts: everything the choice needs, whatever holds the
/// heights (memory: [`Choice::in_memory`]; tiles: `stream::draw::raycast_ranges`).
pub struct Choice<'a> {
    pub mode: Raycast,
    pub layout: &'a BlockLayout,
    /// The true extent in samples.
    pub extent: [u32; 2],
    /// A block's box in the camera's frame: its samples' extent and raw height range.
    pub world_box: WorldBox<'a>,
    pub cam: &'a Camera,
    /// Triangles of a block's outer ring, which a ray-cast block still rasterizes.
    pub ring_triangles: u64,
}

impl<'a> Choice<'a> {
    /// The choice over `hf` in memory, its blocks' ranges from `ranges`.
    pub fn in_memory(
        (mode, cam): (Raycast, &'a Camera),
        layout: &'a BlockLayout,
        hf: &'a Heightfield,
        ranges: &'a BlockRanges,
        ring_triangles: u64,
    ) -> Self {
        let world_box = move |b: &DrawBlock| {
            let (ox, oz) = b.origin(layout);
            let side = layout.block_samples(b.lod) as i64;
            let [lo, hi] = ranges.get(layout, b);
            let hs = hf.height_scale;
            hf.world_box(ox as i64, oz as i64, ox as i64 + side, oz as i64 + side, [lo * hs, hi * hs])
        };
        Choice {
            mode,
            layout,
            extent: [hf.width as u32, hf.height as u32],
            world_box: Box::new(world_box),
            cam,
            ring_triangles,
        }
    }

    /// Whether `b` is ray-cast.
    pub fn casts(&self, b: &DrawBlock) -> bool {
        let ok = || eligible(self.layout, b, self.extent);
        match self.mode {
            Raycast::Off => false,
            Raycast::Checkerboard => (b.bx + b.bz).is_multiple_of(2) && ok(),
            Raycast::All => ok(),
            Raycast::Auto => {
                let replaced = self.layout.triangles_per_block().saturating_sub(self.ring_triangles) as f64;
                ok() && self.box_pixels(b) * RAY_NS_PER_PIXEL < replaced * RASTER_NS_PER_TRIANGLE
            }
        }
    }

    /// Pixels `b`'s box covers ([`box_pixels`]).
    pub fn box_pixels(&self, b: &DrawBlock) -> f64 {
        let (min, max) = (self.world_box)(b);
        box_pixels(self.cam, min, max)
    }
}

/// Whether `b` can be ray-cast: it does not morph, no edge follows a coarser neighbour,
/// and it lies inside the true extent `[0, extent - 1]` (the rasterizer clips the
/// embedding margin; the ray-caster does not).
pub fn eligible(layout: &BlockLayout, b: &DrawBlock, extent: [u32; 2]) -> bool {
    let (ox, oz) = b.origin(layout);
    let side = layout.block_samples(b.lod);
    b.coarser == [0; 4]
        && b.morph == MORPH_ONE
        && b.edge_morph == [MORPH_ONE; 4]
        && ox + side < extent[0]
        && oz + side < extent[1]
}

/// Pixels covered by the box `min`..`max` on `cam`'s screen: the area of its projected
/// corners' convex hull, clipped to the viewport (the whole viewport when a corner lies
/// behind the camera). What a ray-cast block costs in rays: Dick et al.'s estimate, set
/// against its triangles.
pub fn box_pixels(cam: &Camera, min: Vec3, max: Vec3) -> f64 {
    let vp = cam.view_proj();
    let (w, h) = (cam.width as f32, cam.height as f32);
    let mut pts = Vec::with_capacity(8);
    for i in 0..8 {
        let p = Vec3::new(
            if i & 1 == 0 { min.x } else { max.x },
            if i & 2 == 0 { min.y } else { max.y },
            if i & 4 == 0 { min.z } else { max.z },
        );
        match cam.project(&vp, p) {
            Some((x, y)) if (p - cam.position).dot(cam.forward) > cam.near => pts.push(Vec2::new(x, y)),
            _ => return (w * h) as f64,
        }
    }
    let hull = convex_hull(pts);
    let clipped = clip_to_rect(hull, Vec2::ZERO, Vec2::new(w, h));
    polygon_area(&clipped)
}

/// Andrew's monotone chain, counter-clockwise.
fn convex_hull(mut pts: Vec<Vec2>) -> Vec<Vec2> {
    pts.sort_by(|a, b| a.x.total_cmp(&b.x).then(a.y.total_cmp(&b.y)));
    let cross = |o: Vec2, a: Vec2, b: Vec2| (a - o).perp_dot(b - o);
    let mut hull: Vec<Vec2> = Vec::with_capacity(pts.len() * 2);
    for pass in 0..2 {
        let start = hull.len();
        let it: Box<dyn Iterator<Item = &Vec2>> =
            if pass == 0 { Box::new(pts.iter()) } else { Box::new(pts.iter().rev()) };
        for &p in it {
            while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
                hull.pop();
            }
            hull.push(p);
        }
        hull.pop();
    }
    hull
}

/// Sutherland-Hodgman against an axis-aligned rectangle.
fn clip_to_rect(poly: Vec<Vec2>, lo: Vec2, hi: Vec2) -> Vec<Vec2> {
    let mut out = poly;
    // Each edge: (axis, bound, keep values above the bound).
    for (axis, bound, above) in [(0, lo.x, true), (0, hi.x, false), (1, lo.y, true), (1, hi.y, false)] {
        let inside = |p: Vec2| if above { p[axis] >= bound } else { p[axis] <= bound };
        let input = std::mem::take(&mut out);
        for (i, &cur) in input.iter().enumerate() {
            let prev = input[(i + input.len() - 1) % input.len()];
            if inside(cur) != inside(prev) {
                let t = (bound - prev[axis]) / (cur[axis] - prev[axis]);
                out.push(prev + (cur - prev) * t);
            }
            if inside(cur) {
                out.push(cur);
            }
        }
    }
    out
}

fn polygon_area(poly: &[Vec2]) -> f64 {
    let n = poly.len();
    (0..n).map(|i| poly[i].perp_dot(poly[(i + 1) % n]) as f64).sum::<f64>().abs() * 0.5
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_pixels_is_the_clipped_hull() {
        // A thin slab facing a camera that looks straight at it: its face's area.
        let cam = Camera::look_at(Vec3::new(0.0, 0.0, 10.0), Vec3::ZERO, 90.0, 200, 200, 0.1);
        // At distance 10 with a 90 degree field, 20 units span the 200 pixels.
        let px = box_pixels(&cam, Vec3::new(-5.0, -5.0, -0.001), Vec3::new(5.0, 5.0, 0.0));
        assert!((px - 100.0 * 100.0).abs() < 100.0, "{px}");
        // Larger than the view: clipped to it.
        let px = box_pixels(&cam, Vec3::new(-50.0, -50.0, -0.001), Vec3::new(50.0, 50.0, 0.0));
        assert!((px - 200.0 * 200.0).abs() < 1.0, "{px}");
        // Behind the camera's near plane: the whole view (conservative).
        let px = box_pixels(&cam, Vec3::new(-1.0, -1.0, 9.0), Vec3::new(1.0, 1.0, 11.0));
        assert_eq!(px, 200.0 * 200.0);
        // Off screen: nothing.
        let px = box_pixels(&cam, Vec3::new(100.0, -1.0, -1.0), Vec3::new(102.0, 1.0, 1.0));
        assert_eq!(px, 0.0);
    }

    fn layout() -> BlockLayout {
        BlockLayout { n: 6, m: 5, roots: [1, 1] }
    }

    #[test]
    fn only_plain_blocks_inside_the_extent_are_eligible() {
        let l = layout();
        let plain = DrawBlock::new(0, 0, 0);
        assert!(eligible(&l, &plain, [65, 65]));
        // The block's far edge (sample 32) must lie inside the extent.
        assert!(!eligible(&l, &plain, [32, 65]));
        assert!(eligible(&l, &plain, [33, 33]));
        let mut stitched = plain;
        stitched.coarser[2] = 2;
        assert!(!eligible(&l, &stitched, [65, 65]));
        let mut morphing = plain;
        morphing.morph = MORPH_ONE - 1;
        assert!(!eligible(&l, &morphing, [65, 65]));
        let mut edge = plain;
        edge.edge_morph[3] = 0;
        assert!(!eligible(&l, &edge, [65, 65]));
    }

    #[test]
    fn the_choice_follows_the_mode_and_the_cost() {
        let raw: Vec<f32> = (0..65 * 65).map(|i| ((i % 65 * 7 + i / 65 * 3) % 11) as f32).collect();
        let hf =
            Heightfield::embed("test", 65, 65, &raw, crate::lod::heightfield::HeightFormat::Float32, 1.0, 1.0).unwrap();
        let layout = BlockLayout::of(&hf, 33).unwrap();
        let ranges = BlockRanges::of(&hf, &layout);
        let far = Camera::look_at(Vec3::new(-4000.0, 20.0, 16.0), Vec3::new(16.0, 5.0, 16.0), 45.0, 1280, 720, 0.1);
        let near = Camera::look_at(Vec3::new(-10.0, 20.0, 16.0), Vec3::new(16.0, 5.0, 16.0), 45.0, 1280, 720, 0.1);
        let choice = |mode, cam| Choice::in_memory((mode, cam), &layout, &hf, &ranges, 248);
        let (a, b) = (DrawBlock::new(0, 0, 0), DrawBlock::new(0, 1, 0));
        assert!(choice(Raycast::Checkerboard, &near).casts(&a));
        assert!(!choice(Raycast::Checkerboard, &near).casts(&b));
        assert!(!choice(Raycast::Off, &near).casts(&a));
        // Far away a block covers a few pixels: its rays cost less than its triangles.
        assert!(choice(Raycast::Auto, &far).box_pixels(&a) < 50.0);
        assert!(choice(Raycast::Auto, &far).casts(&a));
        assert!(!choice(Raycast::Auto, &near).casts(&a));
        // The block's range is its samples' (both ends included).
        let r = ranges.get(&layout, &a);
        assert_eq!(r, [0.0, 10.0]);
    }
}
