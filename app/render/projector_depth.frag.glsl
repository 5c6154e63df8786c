#version 430
// Projector template, pass 1: writes the bone's linear depth (metres); 0 stays where no bone is.
in float v_depth;
layout(location = 0) out float out_depth;

void main() {
    out_depth = v_depth;
}
