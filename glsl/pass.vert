#version 450
// One triangle covering the target, with no outputs: the errors passes read only
// gl_FragCoord (one fragment per group or block).
void main() {
    vec2 p = vec2(float((gl_VertexIndex << 1) & 2), float(gl_VertexIndex & 2));
    gl_Position = vec4(p * 2.0 - 1.0, 0.0, 1.0);
}
