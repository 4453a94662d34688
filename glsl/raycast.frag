#version 450
// Ray-cast blocks in memory: raycast_frag.glsl.
#extension GL_GOOGLE_include_directive : require
#include "raycast_frag.glsl"
