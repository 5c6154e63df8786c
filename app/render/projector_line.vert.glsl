#version 430
// Projector template, pass 2: the plan's ribbons (lines of a width in metres lying on the bone).
layout(location = 0) in vec3 in_position;   // ribbon vertex, bone frame, metres
layout(location = 1) in vec3 in_normal;     // bone surface normal there, bone frame (outwards)
uniform mat4 T_projector_bone;
uniform mat4 projection;
out float v_depth;
out float v_facing;                         // cosine between the surface normal and the way back to the projector

void main() {
    vec4 p = T_projector_bone * vec4(in_position, 1.0);
    v_depth = p.z;
    vec3 n = mat3(T_projector_bone) * in_normal;
    v_facing = abs(dot(normalize(n), normalize(-p.xyz)));   // the crest is an open surface: either side
    gl_Position = projection * vec4(p.x, -p.y, -p.z, 1.0);
}
