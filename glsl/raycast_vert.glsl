// Ray-cast blocks (SPEC 10, seed 003), the vertex stage of raycast.vert (in memory) and
// stream_raycast.vert (over the atlas: HEIGHTS_ATLAS): the proxy is the block's bounding
// box, made from gl_VertexIndex (6 faces x 2 triangles, no buffers). Only the faces
// turned away from the camera are kept, so every pixel the box covers runs the fragment
// stage once, whether the camera is outside the box or inside it. Positions are relative
// to the anchor sample (in memory the anchor is 0).
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "raycast.glsl"

layout(location = 0) out vec3 v_world;
layout(location = 1) flat out ivec4 v_block;
layout(location = 2) flat out vec4 v_corners;
#ifdef HEIGHTS_ATLAS
// Over the atlas: the block's tile (origin, level, layer) and its raw height range.
layout(location = 3) flat out ivec4 v_tile;
layout(location = 4) flat out vec2 v_range;
#endif

const ivec2 QUAD[6] = ivec2[6](ivec2(0, 0), ivec2(1, 0), ivec2(1, 1), ivec2(0, 0), ivec2(1, 1), ivec2(0, 1));

void main() {
    v_block = block_pc.block;
    v_corners = block_pc.corner_raw;
#ifdef HEIGHTS_ATLAS
    v_tile = block_pc.tile;
    // Over the atlas the range comes with the block (morph.yz: a ray-cast block does
    // not morph); in memory from the min/max pyramid.
    v_range = block_pc.morph.yz;
    vec2 range = block_raw_range(block_pc.block, block_pc.corner_raw, v_range);
#else
    vec2 range = block_raw_range(block_pc.block, block_pc.corner_raw, vec2(0.0));
#endif
    int last = frame.extent.w - 1;
    ivec2 rel = block_pc.block.xy - frame.anchor.xy;
    vec3 lo = vec3(float(rel.x), range.x, float(rel.y));
    vec3 size = vec3(float(last * block_pc.block.z), range.y - range.x, float(last * block_pc.block.z));
    // World units; widened a little so that rays along the box's own faces stay inside.
    vec3 scale = vec3(frame.spacing.x, frame.terrain.y, frame.spacing.y);
    vec3 bmin = lo * scale;
    vec3 bmax = (lo + size) * scale;
    vec3 pad = max(abs(bmax - bmin) * 3e-2, vec3(1e-3));
    bmin -= pad;
    bmax += pad;

    int face = gl_VertexIndex / 6;
    int axis = face >> 1;
    bool high = (face & 1) == 1;
    ivec2 uv = QUAD[gl_VertexIndex % 6];
    int a1 = (axis + 1) % 3;
    int a2 = (axis + 2) % 3;
    vec3 p;
    p[axis] = high ? bmax[axis] : bmin[axis];
    p[a1] = uv.x == 1 ? bmax[a1] : bmin[a1];
    p[a2] = uv.y == 1 ? bmax[a2] : bmin[a2];
    v_world = p;
    vec3 cam = frame.camera_fog.xyz;
    // A face the camera sees from outside is a front face: collapsed outside the view.
    bool front = high ? cam[axis] > bmax[axis] : cam[axis] < bmin[axis];
    gl_Position = front ? vec4(2.0, 2.0, 2.0, 1.0) : frame.view_proj * vec4(p, 1.0);
}
