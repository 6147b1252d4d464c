/* The counter-based random streams of lifelong operation (the reference: sim/streams.py
 * uniform): SplitMix64's finaliser, in wrapping uint64 arithmetic (the reference's wrapping
 * int64 with logical shifts), the same float64 draws. */
#ifndef AGV_STREAMS_H
#define AGV_STREAMS_H

#include "common.h"

static inline uint64_t stream_mix(uint64_t z) {
    z = (z ^ (z >> 30)) * 0xBF58476D1CE4E5B9ULL;
    z = (z ^ (z >> 27)) * 0x94D049BB133111EBULL;
    return z ^ (z >> 31);
}

/* One counter folded into a stream state: the reference's mix(z + (c + 1) * golden). */
static inline uint64_t stream_fold(uint64_t z, int64_t counter) {
    return stream_mix(z + ((uint64_t)counter + 1) * 0x9E3779B97F4A7C15ULL);
}

/* The draw of a state whose counters are all folded in: 53 random bits in [0, 1). */
static inline double stream_unit(uint64_t z) {
    return (double)(stream_mix(z) >> 11) * (1.0 / 9007199254740992.0);
}

/* out[k] = uniform(key[k], counters[0][k], ..., counters[nc - 1][k]), k < K. */
void agv_uniform(int64_t K, int64_t nc, const int64_t *key, const int64_t *counters,
                 double *out) {
    for (int64_t k = 0; k < K; k++) {
        uint64_t z = (uint64_t)key[k];
        for (int64_t c = 0; c < nc; c++) z = stream_fold(z, counters[c * K + k]);
        out[k] = stream_unit(z);
    }
}

/* The breakdowns of one step (sim/lifelong.py LifelongEnv._breakdowns): out[b, i] = can[b, i]
 * and uniform(key[b], stream, step[b], i) < rate, the same draws as agv_uniform. */
void agv_fault_draws(int64_t B, int64_t N, const int64_t *key, int64_t stream,
                     const int64_t *step, double rate, const uint8_t *can, uint8_t *out) {
    for (int64_t b = 0; b < B; b++) {
        const uint64_t z0 = stream_fold(stream_fold((uint64_t)key[b], stream), step[b]);
        for (int64_t i = 0; i < N; i++) {
            const double u = stream_unit(stream_fold(z0, i));
            out[b * N + i] = can[b * N + i] && u < rate;
        }
    }
}

#endif
