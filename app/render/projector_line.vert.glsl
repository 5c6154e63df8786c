#version 430
// Projector template, pass 2: the plan's ribbons (lines of a width in metres lying on the bone).
layout(location = 0) in vec3 in_position;   // ribbon vertex, bone frame, metres
uniform mat4 T_projector_bone;
uniform mat4 projection;
out float v_depth;

void main() {
    vec4 p = T_projector_bone * vec4(in_position, 1.0);
    v_depth = p.z;
    gl_Position = projection * vec4(p.x, -p.y, -p.z, 1.0);
}
