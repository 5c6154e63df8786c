#version 430
// Projector template, pass 1: the bone's linear depth seen from the projector (app/projector/render.py).
layout(location = 0) in vec3 in_position;   // bone frame, metres
uniform mat4 T_projector_bone;              // pose of the bone in the projector's OpenCV frame
uniform mat4 projection;                    // OpenGL projection from K_p (PinholeCamera.opengl_projection)
out float v_depth;                          // z in the projector frame, metres

void main() {
    vec4 p = T_projector_bone * vec4(in_position, 1.0);
    v_depth = p.z;
    // OpenCV -> OpenGL eye coordinates: negate y and z (the renderer's only convention flip).
    gl_Position = projection * vec4(p.x, -p.y, -p.z, 1.0);
}
