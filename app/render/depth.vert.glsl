#version 430
// Batched depth rendering: instance i draws the mesh at pose T_camera_object[FIRST_INSTANCE + i]
// into tile i of a large texture (DESIGN.md "Rendering all hypotheses at once", (A) III.C).
// Injected: nothing; uniforms below.
layout(location = 0) in vec3 in_position;  // object (bone) frame, metres

// 4x4 poses of the object in the OpenCV camera frame, uploaded column-major (see batched.py).
layout(std430, binding = 0) readonly buffer Poses { mat4 T_camera_object[]; };

uniform mat4 projection;     // OpenGL projection built from K (PinholeCamera.opengl_projection)
uniform ivec2 grid;          // tiles per row, tile rows
uniform int first_instance;  // offset into Poses (the scene renderer draws one object per call)

out float v_depth;           // linear depth: z in the OpenCV camera frame, metres

void main() {
    int id = gl_InstanceID + first_instance;
    vec4 p_camera = T_camera_object[id] * vec4(in_position, 1.0);
    v_depth = p_camera.z;
    // OpenCV -> OpenGL eye coordinates: negate y and z (the renderer's only convention flip).
    vec4 clip = projection * vec4(p_camera.x, -p_camera.y, -p_camera.z, 1.0);
    // Clip each instance to its own tile: the tile is the [-1, 1] square of its own clip space.
    gl_ClipDistance[0] = clip.w + clip.x;
    gl_ClipDistance[1] = clip.w - clip.x;
    gl_ClipDistance[2] = clip.w + clip.y;
    gl_ClipDistance[3] = clip.w - clip.y;
    // Then move the tile into place: ndc_big = (ndc + 1) / grid + 2 tile / grid - 1.
    vec2 tile = vec2(float(gl_InstanceID % grid.x), float(gl_InstanceID / grid.x));
    vec2 scale = 1.0 / vec2(grid);
    clip.xy = (clip.xy + clip.w) * scale + (2.0 * tile * scale - 1.0) * clip.w;
    gl_Position = clip;
}
