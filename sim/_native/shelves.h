/* Discs against rectangular shelves: sim/physics.py's collide_obstacles, for the lifelong
 * step (sim/lifelong.py), in place on the physics step's fresh position and velocity.
 *
 * For every disc and every shelf: the closest point of the rectangle, the distance to it; a
 * centre inside leaves through the nearest face (the first of left, bottom, right, top at
 * equal depth); the pushes and the cancelled inward velocities of every shelf the disc
 * overlaps add up, as in the torch reference, bit for bit (tests/sim/test_shelves_native.py).
 * Every disc is moved, as in the reference; mpe_step keeps the positions of the AGVs that do
 * not move. */
#ifndef AGV_SHELVES_H
#define AGV_SHELVES_H

#include "common.h"

void agv_collide_shelves(int64_t n, float *pos, float *vel, int64_t K, const float *rects,
                         float radius, int fused) {
    for (int64_t i = 0; i < n; i++) {
        const float px = pos[2 * i], py = pos[2 * i + 1];
        const float vx = vel[2 * i], vy = vel[2 * i + 1];
        float push_x = 0.0f, push_y = 0.0f, cut_x = 0.0f, cut_y = 0.0f;
        for (int64_t k = 0; k < K; k++) {
            const float lx = rects[4 * k], ly = rects[4 * k + 1];
            const float hx = rects[4 * k + 2], hy = rects[4 * k + 3];
            const float cx = fminf(fmaxf(px, lx), hx), cy = fminf(fmaxf(py, ly), hy);
            const float dx = px - cx, dy = py - cy;
            /* torch.linalg.vector_norm of a float32 pair: sqrt(fma(dy, dy, dx * dx)) or
             * sqrt(dx * dx + dy * dy), as the caller found torch to round. */
            const float dist = fused ? sqrtf(fmaf(dy, dy, dx * dx)) : sqrtf(dx * dx + dy * dy);
            if (dist >= radius) continue;  /* depth <= 0: no contact */
            float nx, ny, depth;
            if (dist <= 1e-9f) {
                const float faces[4] = {px - lx, py - ly, hx - px, hy - py};
                int f = 0;
                for (int j = 1; j < 4; j++) if (faces[j] < faces[f]) f = j;
                nx = f == 0 ? -1.0f : (f == 2 ? 1.0f : 0.0f);
                ny = f == 1 ? -1.0f : (f == 3 ? 1.0f : 0.0f);
                depth = faces[f] + radius;
            } else {
                const float s = fmaxf(dist, 1e-9f);
                nx = dx / s;
                ny = dy / s;
                depth = radius - dist;
            }
            if (!(depth > 0.0f)) continue;
            push_x += nx * depth;
            push_y += ny * depth;
            const float inward = fminf(vx * nx + vy * ny, 0.0f);
            cut_x += nx * inward;
            cut_y += ny * inward;
        }
        pos[2 * i] = px + push_x;
        pos[2 * i + 1] = py + push_y;
        vel[2 * i] = vx - cut_x;
        vel[2 * i + 1] = vy - cut_y;
    }
}

#endif
