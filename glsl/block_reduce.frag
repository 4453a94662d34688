#version 450
// One fragment per drawable block of LOD j: the max over the (k-1)^2 group centres of
// LOD j it covers (seed 000, section 3.3, TBE).
#extension GL_GOOGLE_include_directive : require
#define USE_ReducePush
#include "layout.glsl"

layout(set = 0, binding = REDUCE_BINDING_GIE) uniform sampler2D gie;
layout(location = 0) out float out_tbe;

void main() {
    int mip = reduce_pc.level.y;
    int groups = reduce_pc.level.z;
    ivec2 base = ivec2(gl_FragCoord.xy) * groups;
    float m = 0.0;
    for (int z = 0; z < groups; z++) {
        for (int x = 0; x < groups; x++) {
            m = max(m, texelFetch(gie, base + ivec2(x, z), mip).r);
        }
    }
    out_tbe = m;
}
