#version 450
// Ray-cast blocks over the atlas (streamed frames): raycast_vert.glsl.
#extension GL_GOOGLE_include_directive : require
#define HEIGHTS_ATLAS
#include "raycast_vert.glsl"
