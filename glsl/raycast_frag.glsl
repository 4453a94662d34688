// Ray-cast blocks (SPEC 10, seed 003), the fragment stage of raycast.frag (in memory)
// and stream_raycast.frag (over the atlas: HEIGHTS_ATLAS): the ray through this pixel's centre meets exactly
// the triangles the block's rasterized self would draw (its vertices, the resolved
// corners, quads split along the a-i diagonal; only blocks that neither morph nor stitch
// are ray-cast), nearest first, seen from above as the rasterizer's back-face culling
// sees them. Cells of 4 x 4 quads whose min/max the ray passes above or below are
// skipped. The hit's depth is written; a ray that meets nothing is discarded, so the
// deferred shading pass shades a ray-cast pixel as any other.
#define USE_FrameUniforms
#include "layout.glsl"
#include "raycast.glsl"

layout(location = 0) in vec3 v_world;
layout(location = 1) flat in ivec4 v_block;
layout(location = 2) flat in vec4 v_corners;
#ifdef HEIGHTS_ATLAS
layout(location = 3) flat in ivec4 v_tile;
layout(location = 4) flat in vec2 v_range;
#else
// In memory heights and ranges need no tile (an unused input would be a validation
// warning).
const ivec4 v_tile = ivec4(0);
const vec2 v_range = vec2(0.0);
#endif

// Slack of the intersection tests, in quads: a ray through the shared edge of two quads
// or triangles is caught by both rather than by neither. The ray starts at the box and
// heights are taken from the block's lowest, so rounding is that of numbers of about a
// block's size (1e-5 quads at most), well inside it. Where the block meets another,
// whose coverage the rasterizer decides (vertices snapped to 1/256 of a pixel), its
// outer ring of quads is rasterized too (blocks.rs), so that boundary is the
// rasterizer's own on both sides.
const float EPS = 1e-3;
// The same slack along the ray (its parameter; the direction is a unit vector in block
// units, mostly raw height units when the ray is steep).
float t_slack;
// Raw height the block's heights are taken from.
float base;
// How far the surface is lifted for the ray (raw units): 1/16 of a pixel at the
// distance of the cell the ray is in (`lift_per_m` times it). The rasterizer decides
// coverage with vertices snapped to 1/256 of a pixel, so a ray grazing a ridge the
// rasterizer covers may pass a hair above it; the lift makes the ray-caster cover at
// least what the rasterizer does. Each cell lifts its own quads by its own amount:
// every quad still holds its unlifted self, so the surface stays closed.
float lift;
float lift_per_m;
// Block units to world: world = block * scale + origin.
vec3 scale;
vec3 origin;
const float LIFT_PX = 1.0 / 16.0;

int last_quad() {
    return frame.extent.w - 1;
}

float vertex_raw(ivec2 q) {
    int last = last_quad();
    if (q == ivec2(0, 0)) return v_corners.x;
    if (q == ivec2(last, 0)) return v_corners.y;
    if (q == ivec2(last, last)) return v_corners.z;
    if (q == ivec2(0, last)) return v_corners.w;
    return block_vertex_raw(v_block, v_tile, q);
}

// A height relative to `base`.
float vertex_y(ivec2 q) {
    return vertex_raw(q) - base;
}

// The ray in block units: x, z in quads from the block's origin, y raw height, at
// parameter t (t = 1 at this fragment's point on the box).
vec3 ray_o;
vec3 ray_d;

vec3 at(float t) {
    return ray_o + t * ray_d;
}

// The lift for a cell the ray enters at parameter `t`.
float lift_at(float t) {
    return lift_per_m * length(at(t) * scale + origin - frame.camera_fog.xyz);
}

// Whether the ray over [ta, tb] (widened by the slack) meets heights in `range`: cells
// it passes wholly above or below are skipped.
bool spans(float ta, float tb, vec2 range) {
    float ya = at(ta - t_slack).y;
    float yb = at(tb + t_slack).y;
    return min(ya, yb) <= range.y + lift && max(ya, yb) >= range.x;
}

// Where the ray meets the plane y = A + B.x fx + B.y fz (fx, fz from the quad's corner)
// lifted by `lift`, if that lies in the quad on the side of the diagonal `upper`
// (fz >= fx) or not: its crossing from above, or `ta` (where the ray enters the quad)
// when it enters, descending, between the plane and its lift (a grazing ray meets the lifted plane
// earlier along it, perhaps before this quad). Whether the point lies in the quad
// decides, not the ray's span over the quad: the same test in both quads of an edge.
float plane_hit(ivec2 q, float a, vec2 b, bool upper, float ta) {
    vec2 f0 = ray_o.xz - vec2(q);
    float g0 = ray_o.y - (a + lift + dot(b, f0));
    float g1 = ray_d.y - dot(b, ray_d.xz);
    // Descending towards the plane only: the rasterizer culls the underside (and a
    // camera under the surface sees through it).
    if (g1 >= 0.0) return 1e30;
    float g_in = g0 + g1 * ta;
    float t = g_in <= 0.0 && g_in >= -lift ? ta : -g0 / g1;
    vec2 f = f0 + t * ray_d.xz;
    float side = upper ? f.y - f.x : f.x - f.y;
    if (side < -EPS || any(lessThan(f, vec2(-EPS))) || any(greaterThan(f, vec2(1.0 + EPS)))) return 1e30;
    return t;
}

// The two triangles of quad q: a (0,0) c (1,0) g (0,1) i (1,1), split along a-i.
float quad_hit(ivec2 q, float ta, float tb) {
    lift = lift_at(ta);
    float ha = vertex_y(q);
    float hc = vertex_y(q + ivec2(1, 0));
    float hg = vertex_y(q + ivec2(0, 1));
    float hi = vertex_y(q + ivec2(1, 1));
    if (!spans(ta, tb, vec2(min(min(ha, hc), min(hg, hi)), max(max(ha, hc), max(hg, hi))))) return 1e30;
    // fx >= fz: a, c, i.  fz >= fx: a, i, g.
    float t1 = plane_hit(q, ha, vec2(hc - ha, hi - hc), false, ta);
    float t2 = plane_hit(q, ha, vec2(hi - hg, hg - ha), true, ta);
    return min(t1, t2);
}

// Steps of a 2D DDA over cells of `size` quads from parameter t in cell c.
struct Walk {
    ivec2 cell;
    ivec2 step;
    vec2 next;
    vec2 delta;
};

Walk walk_from(float t, int size, ivec2 lo, ivec2 hi) {
    vec2 p = at(t).xz / float(size);
    Walk w;
    w.cell = clamp(ivec2(floor(p)), lo, hi);
    w.step = ivec2(ray_d.x >= 0.0 ? 1 : -1, ray_d.z >= 0.0 ? 1 : -1);
    vec2 d = ray_d.xz / float(size);
    vec2 inv = vec2(abs(d.x) > 1e-12 ? 1.0 / d.x : 1e30, abs(d.y) > 1e-12 ? 1.0 / d.y : 1e30);
    vec2 edge = vec2(w.cell + max(w.step, ivec2(0)));
    w.next = vec2(abs(d.x) > 1e-12 ? (edge.x - ray_o.x / float(size)) * inv.x : 1e30,
                  abs(d.y) > 1e-12 ? (edge.y - ray_o.z / float(size)) * inv.y : 1e30);
    w.delta = abs(inv);
    return w;
}

// Into the next cell, across the nearer of its two next edges.
void advance(inout Walk w) {
    if (w.next.x < w.next.y) {
        w.cell.x += w.step.x;
        w.next.x += w.delta.x;
    } else {
        w.cell.y += w.step.y;
        w.next.y += w.delta.y;
    }
}

// The ray's parameters entering and leaving the box (entering clamped to 0).
vec2 box_span(vec3 bmin, vec3 bmax) {
    vec3 inv = 1.0 / ray_d;
    vec3 ta = (bmin - ray_o) * inv;
    vec3 tb = (bmax - ray_o) * inv;
    vec3 lo = min(ta, tb);
    vec3 hi = max(ta, tb);
    return vec2(max(max(max(lo.x, lo.y), lo.z), 0.0), min(min(hi.x, hi.y), hi.z));
}

// Where the ray enters the block's columns (x and z only).
float columns_entry(vec3 bmin, vec3 bmax) {
    vec2 inv = 1.0 / ray_d.xz;
    vec2 ta = (bmin.xz - ray_o.xz) * inv;
    vec2 tb = (bmax.xz - ray_o.xz) * inv;
    vec2 lo = min(ta, tb);
    return max(max(lo.x, lo.y), 0.0);
}

void main() {
    // Before anything that varies per pixel: derivatives need the whole 2x2 quad.
    vec3 to_face = v_world - frame.camera_fog.xyz;
    float pixel_angle = length(fwidth(normalize(to_face)));
    lift_per_m = LIFT_PX * pixel_angle / frame.terrain.y;
    int last = last_quad();
    float stride = float(v_block.z);
    vec3 cam = frame.camera_fog.xyz;
    scale = vec3(frame.spacing.x * stride, frame.terrain.y, frame.spacing.y * stride);
    ivec2 rel = v_block.xy - frame.anchor.xy;
    origin = vec3(float(rel.x) * frame.spacing.x, 0.0, float(rel.y) * frame.spacing.y);
    vec2 range = block_raw_range(v_block, v_corners, v_range);
    base = range.x;
    origin.y = base * frame.terrain.y;
    ray_o = (cam - origin) / scale;
    ray_d = normalize((v_world - origin) / scale - ray_o);
    t_slack = EPS / max(max(abs(ray_d.x), abs(ray_d.z)), 1e-6);

    // The ray's span inside the block's box (quads, heights from `base`).
    // Lifted as far as anywhere in it: by the lift at the far face.
    lift = lift_per_m * length(to_face);
    vec3 bmin = vec3(0.0);
    vec3 bmax = vec3(float(last), range.y - base + lift, float(last));
    // Restart the ray twice: the camera may be thousands of quads away, where a float
    // step is larger than EPS. First where it enters the block's columns (x and z alone
    // are exact enough), then, from there, where it enters the box: from far away the
    // top face's crossing of a grazing ray is off by whole quads.
    vec2 t_box = box_span(bmin, bmax);
    if (t_box.x > t_box.y) discard;
    float start = max(columns_entry(bmin, bmax) - t_slack, 0.0);
    ray_o = at(start);
    t_box = box_span(bmin, bmax);
    start = max(t_box.x - t_slack, 0.0);
    ray_o = at(start);
    float t0 = t_box.x - start;
    float t1 = t_box.y - start + t_slack;

    int coarse = min(4, last);
    int cells = last / coarse;
    float best = 1e30;
    Walk outer = walk_from(t0, coarse, ivec2(0), ivec2(cells - 1));
    float t = t0;
    for (int i = 0; i < 2 * cells + 2 && t <= t1 && best > 1e29; i++) {
        float t_out = min(min(outer.next.x, outer.next.y), t1);
        vec2 mm = cell_raw_range(v_block, v_corners, v_range, outer.cell * coarse, coarse) - base;
        // The largest lift of the cell's quads: the one where the ray leaves it.
        lift = lift_at(t_out + t_slack);
        if (spans(t, t_out, mm)) {
            ivec2 first = outer.cell * coarse;
            Walk inner = walk_from(t, 1, first, first + coarse - 1);
            float s = t;
            for (int j = 0; j < 2 * coarse + 2 && s <= t_out; j++) {
                float s_out = min(min(inner.next.x, inner.next.y), t_out);
                best = min(best, quad_hit(inner.cell, s, s_out));
                if (best < 1e29) break;
                advance(inner);
                s = s_out;
                if (any(lessThan(inner.cell, first)) || any(greaterThan(inner.cell, first + coarse - 1))) break;
            }
        }
        advance(outer);
        t = t_out;
        if (any(lessThan(outer.cell, ivec2(0))) || any(greaterThan(outer.cell, ivec2(cells - 1)))) break;
    }
    if (best > 1e29) discard;
    vec3 hit = at(best) * scale + origin;
    // Beyond the true extent the rasterizer clips the block (terrain_depth.vert).
    vec2 far_edge = vec2(frame.extent.xy - 1 - frame.anchor.xy) * frame.spacing.xy;
    if (hit.x > far_edge.x || hit.z > far_edge.y) discard;
    vec4 clip = frame.view_proj * vec4(hit, 1.0);
    gl_FragDepth = clip.z / clip.w;
}
