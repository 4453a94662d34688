#version 450
// Ray-cast blocks (SPEC 10, seed 003): the proxy is the block's bounding box, made from
// gl_VertexIndex (6 faces x 2 triangles, no buffers). Only the faces turned away from
// the camera are kept, so every pixel the box covers runs raycast.frag once, whether the
// camera is outside the box or inside it.
#extension GL_GOOGLE_include_directive : require
#define USE_BlockPush
#define USE_FrameUniforms
#include "layout.glsl"
#include "raycast.glsl"

layout(location = 0) out vec3 v_world;
layout(location = 1) flat out ivec4 v_block;
layout(location = 2) flat out vec4 v_corners;

const ivec2 QUAD[6] = ivec2[6](ivec2(0, 0), ivec2(1, 0), ivec2(1, 1), ivec2(0, 0), ivec2(1, 1), ivec2(0, 1));

void main() {
    v_block = block_pc.block;
    v_corners = block_pc.corner_raw;
    vec2 range = block_raw_range(block_pc.block, block_pc.corner_raw);
    int last = frame.extent.w - 1;
    vec3 lo = vec3(float(block_pc.block.x), range.x, float(block_pc.block.y));
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
