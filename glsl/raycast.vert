#version 450
// Ray-cast blocks in memory: raycast_vert.glsl.
#extension GL_GOOGLE_include_directive : require
#include "raycast_vert.glsl"
