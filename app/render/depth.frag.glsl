#version 430
// Writes linear camera depth (metres) and, for scene rendering, the object's label.
in float v_depth;
uniform float label;  // object label for scene rendering (0 = background)
layout(location = 0) out float out_depth;
layout(location = 1) out float out_label;

void main() {
    out_depth = v_depth;
    out_label = label;
}
