// Helpers shared by the terrain and errors shaders. Heights are stored raw (the file's
// units); world height = raw * height_scale, computed in the same order as the CPU.

// R16_UNORM returns raw/65535; recover the exact integer so that the GPU and the CPU
// work on bit-identical values.
float decode_raw(float texel, int unorm16) {
    return unorm16 != 0 ? round(texel * 65535.0) : texel;
}
