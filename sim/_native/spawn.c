/* Spawning's candidate check (the torch reference: sim/scenarios.py Scenario.spawn).
 * Compiled as part of kernels.c. */
#include "common.h"

/* One round of spawning for entity k (Scenario.spawn): for each of the b environments still
 * to place, the first of its C candidates (b, C, 2) that passes ok (b, C; NULL = all) and
 * keeps squared distance >= gap2[j] to every earlier entity j < k of placed (B, E, 2). The
 * squared distance is summed as torch does, (dx * dx) + (dy * dy) in float32, so both paths
 * accept the same candidates. Writes placed[todo[i], k] and found[i]. */
void agv_spawn_pick(int64_t b, int64_t C, int64_t E, int64_t k, const float *cand,
                    const uint8_t *ok, const int64_t *todo, const float *gap2, float *placed,
                    uint8_t *found) {
    for (int64_t i = 0; i < b; i++) {
        float *row = placed + todo[i] * E * 2;
        found[i] = 0;
        for (int64_t c = 0; c < C && !found[i]; c++) {
            if (ok != NULL && !ok[i * C + c]) continue;
            const float cx = cand[(i * C + c) * 2], cy = cand[(i * C + c) * 2 + 1];
            int clear = 1;
            for (int64_t j = 0; j < k && clear; j++) {
                const float dx = cx - row[2 * j], dy = cy - row[2 * j + 1];
                const float sx = dx * dx, sy = dy * dy;
                clear = sx + sy >= gap2[j];
            }
            if (clear) {
                row[2 * k] = cx;
                row[2 * k + 1] = cy;
                found[i] = 1;
            }
        }
    }
}
