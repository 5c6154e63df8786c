#version 430
// Projector template, pass 2: light a ribbon fragment only where it lies on the visible bone
// surface: the bone's depth at this pixel (pass 1) exists and is not in front of the ribbon by more
// than DEPTH_TOLERANCE (metres, injected), and the surface faces the projector by more than
// MIN_FACING (cosine, injected): at grazing incidence a line of light smears along the surface.
// Hidden parts of the outline, grazing parts and parts off the bone stay black.
in float v_depth;
in float v_facing;
uniform sampler2D bone_depth;   // (W, H) linear depth of the bone from pass 1, 0 = no bone
uniform vec3 color;             // the outline's colour, 0..1
layout(location = 0) out vec4 out_color;

void main() {
    float bone = texelFetch(bone_depth, ivec2(gl_FragCoord.xy), 0).r;
    if (bone <= 0.0 || v_depth > bone + DEPTH_TOLERANCE || v_facing < MIN_FACING) {
        discard;
    }
    out_color = vec4(color, 1.0);
}
