#version 430
// Per-particle log-likelihood of the measured depth image given the rendered tile
// (DESIGN.md "Observation"; numpy reference: app/filter/likelihood_ref.py, which this must match).
// One work group per particle; each invocation sums a strided subset of the tile's pixels, then a
// shared-memory tree reduction; invocation 0 writes one float. Only N floats are read back.
// Injected: LOCAL_SIZE (power of two), TILE_W, TILE_H, GRID_X, SMOOTH_OCCLUSION (0/1),
// CLASSIFICATION (0/1), BACKGROUND_RATIO (0/1), LOG_FLOOR (the probability floor inside the log, as in the reference).
layout(local_size_x = LOCAL_SIZE) in;

layout(binding = 0) uniform sampler2D rendered;   // tiled linear depth, GL row order, 0 = not covered
layout(binding = 1) uniform sampler2D measured;   // h x w measured depth in image row order, <= 0 = invalid
layout(std430, binding = 2) writeonly buffer LogLikelihood { float log_likelihood[]; };
// Per particle, the image-space box (u0, v0, u1, v1), inclusive, that holds its whole rendering
// (projected bounding box of the mesh, clamped to the tile): pixels outside it are not covered.
layout(std430, binding = 3) readonly buffer Boxes { ivec4 box[]; };

uniform float z_max;        // m, range of the uniform outlier density p_u = 1 / z_max
uniform float lam;          // 1/m, rate of the occlusion exponential
uniform float w_u;          // mixture weights
uniform float w_e;
uniform float w_n;
uniform float k_noise;      // 1/m, sigma(z) = k z^2 + sigma_base
uniform float sigma_base;   // m
uniform float l0_weight;    // L0 penalty per background-classified pixel ((B) eq. 4.38-4.39)
uniform float c_reg;        // pixel-count regularisation ((B) eq. 4.37); 0 = off
uniform float pixel_weight; // alpha, tempering of the sum over pixels (1 = plain product)
uniform float occluder_margin; // m, with BACKGROUND_RATIO a pixel this far in front of z* is neutral

shared float partial_sum[LOCAL_SIZE];
shared float partial_count[LOCAL_SIZE];

const float SQRT1_2 = 0.70710678118654752;
const float INV_SQRT_2PI = 0.39894228040143268;

// erfc for x >= 0, Abramowitz & Stegun 7.1.26 (|error| < 1.5e-7).
float erfc_pos(float x) {
    float t = 1.0 / (1.0 + 0.3275911 * x);
    float poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))));
    return poly * exp(-x * x);
}

// Standard normal CDF Phi(x) = 0.5 erfc(-x / sqrt 2).
float normal_cdf(float x) {
    float e = 0.5 * erfc_pos(abs(x) * SQRT1_2);
    return x >= 0.0 ? 1.0 - e : e;
}

float safe_log(float p) { return log(max(p, LOG_FLOOR)); }

// Occlusion density p_e(z | z*): truncated exponential, or (B) eq. 4.33 smoothed by the noise.
float occlusion_density(float z, float z_star, float sigma) {
    float norm = lam / (1.0 - exp(-lam * z_star));
#if SMOOTH_OCCLUSION
    float s2 = lam * sigma * sigma;
    float window = normal_cdf((z_star - z + s2) / sigma) - normal_cdf((s2 - z) / sigma);
    return norm * exp(-lam * z + 0.5 * lam * s2) * window;
#else
    return (z > 0.0 && z < z_star) ? norm * exp(-lam * z) : 0.0;
#endif
}

float beam_log_likelihood(float z, float z_star) {
    float p_u = w_u / z_max;
    bool valid = z > 0.0 && z <= z_max && !isinf(z) && !isnan(z);
#if CLASSIFICATION
    if (!valid) return safe_log(p_u) - l0_weight;
    float sigma = k_noise * z_star * z_star + sigma_base;
    float r = (z - z_star) / sigma;
    float l_obj = safe_log(w_n * INV_SQRT_2PI / sigma * exp(-0.5 * r * r));
    float l_bg = safe_log(p_u + w_e * occlusion_density(z, z_star, sigma));
    return l_obj >= l_bg ? l_obj : l_bg - l0_weight;
#else
    if (!valid) return safe_log(p_u);
    float sigma = k_noise * z_star * z_star + sigma_base;
    float r = (z - z_star) / sigma;
    float p_n = INV_SQRT_2PI / sigma * exp(-0.5 * r * r);
    return safe_log(p_u + w_e * occlusion_density(z, z_star, sigma) + w_n * p_n);
#endif
}

// The per-pixel term; with BACKGROUND_RATIO the log-ratio to the uniform background hypothesis
// p_0 = 1 / z_max for valid pixels (invalid pixels: ratio to w_u p_u), and 0 for a pixel that
// sees an occluder more than occluder_margin in front of z*, as in the reference.
float pixel_log_likelihood(float z, float z_star) {
    float l = beam_log_likelihood(z, z_star);
#if BACKGROUND_RATIO
    bool valid = z > 0.0 && z <= z_max && !isinf(z) && !isnan(z);
    if (valid && z < z_star - occluder_margin) return 0.0;
    l -= valid ? log(1.0 / z_max) : safe_log(w_u / z_max);
#endif
    return l;
}

void main() {
    uint particle = gl_WorkGroupID.x;
    uint lid = gl_LocalInvocationID.x;
    ivec2 tile_origin = ivec2(int(particle % uint(GRID_X)) * TILE_W, int(particle / uint(GRID_X)) * TILE_H);
    ivec4 b = box[particle];
    int box_w = max(b.z - b.x + 1, 0);
    int box_h = max(b.w - b.y + 1, 0);
    float sum = 0.0;
    float count = 0.0;
    for (uint i = lid; i < uint(box_w * box_h); i += uint(LOCAL_SIZE)) {
        int u = b.x + int(i % uint(box_w));
        int v = b.y + int(i / uint(box_w));
        // GL rows run bottom-up inside the tile: image row v is tile row TILE_H - 1 - v.
        float z_star = texelFetch(rendered, tile_origin + ivec2(u, TILE_H - 1 - v), 0).r;
        if (z_star <= 0.0) continue;  // pose does not cover this pixel: log 1 = 0
        float z = texelFetch(measured, ivec2(u, v), 0).r;
        sum += pixel_log_likelihood(z, z_star);
        count += 1.0;
    }
    partial_sum[lid] = sum;
    partial_count[lid] = count;
    barrier();
    for (uint stride = uint(LOCAL_SIZE) / 2u; stride > 0u; stride /= 2u) {
        if (lid < stride) {
            partial_sum[lid] += partial_sum[lid + stride];
            partial_count[lid] += partial_count[lid + stride];
        }
        barrier();
    }
    if (lid == 0u) {
        float total = partial_sum[0];
        if (c_reg > 0.0) total = c_reg * total / max(partial_count[0], 1.0);
        else total = pixel_weight * total;
        log_likelihood[particle] = total;
    }
}
