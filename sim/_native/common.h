/* Shared by every kernel: the scratch arena, the small-scene sizes and their
 * specialisation, the lane vectors of the small scenes, and a kernel call's scratch. */
#ifndef AGV_COMMON_H
#define AGV_COMMON_H

#include <math.h>
#include <stdint.h>
#include <stdlib.h>
#include <string.h>

#define INF_F ((float)INFINITY)

/* Hot loops that gain from wider vectors get an AVX2 clone beside the default one, picked at
 * load time by the CPU (GCC's target_clones; x86-64 only). No FMA contraction is allowed
 * (-ffp-contract=off) and no reduction is reordered (no -ffast-math), so both clones give
 * bit-identical results: only elementwise loops get wider. */
#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__) && !defined(AGV_NO_CLONES)
#define AGV_WIDE __attribute__((target_clones("avx2", "default")))
#else
#define AGV_WIDE
#endif

/* A per-thread scratch buffer that only grows (released at exit). */
static __thread unsigned char *arena_buf = NULL;
static __thread size_t arena_len = 0;

static void *arena_reserve(size_t bytes) {
    if (bytes > arena_len) {
        free(arena_buf);
        arena_buf = malloc(bytes);
        arena_len = arena_buf ? bytes : 0;
    }
    return arena_buf;
}
/* Small fixed sizes: stack scratch up to this many AGVs or tasks, heap beyond. */
#define SMALL 8

/* Scenes of VL + 1 to SMALL AGVs and at most SMALL tasks are done with all AGVs at once: AGV i
 * sits in lane i % VL of vector i / VL (GCC and Clang vector extensions; plain SSE2 on
 * x86-64). Up to VL AGVs the scalar code is faster: one vector would be mostly empty. */
#define VL 4
#define CH (SMALL / VL)
typedef float vf __attribute__((vector_size(4 * VL)));
typedef int32_t vi __attribute__((vector_size(4 * VL)));

static inline __attribute__((always_inline)) vf vf_sqrt(vf x) {
    vf r;
    for (int l = 0; l < VL; l++) r[l] = sqrtf(x[l]);  /* one instruction where there is one */
    return r;
}

/* mask ? y : x, lane by lane (mask lanes are 0 or -1). */
static inline __attribute__((always_inline)) vf vf_pick(vi mask, vf y, vf x) {
    return (vf)((mask & (vi)y) | (~mask & (vi)x));
}

/* Whether a scene of N AGVs and M tasks is done in lanes. */
#define USES_LANES(N, M) (VL < (N) && (N) <= SMALL && (M) <= SMALL)

/* {0, 1, ..., VL - 1}: each lane's index. */
static inline __attribute__((always_inline)) vi vi_lanes(void) {
    vi r;
    for (int l = 0; l < VL; l++) r[l] = l;
    return r;
}

static inline __attribute__((always_inline)) vf vf_fill(float x) {
    vf r;
    for (int l = 0; l < VL; l++) r[l] = x;
    return r;
}

/* The distances of a small scene in lanes: dt[j] from the AGVs to task j, da[j] to AGV j
 * (0 to itself). Each is sqrt(dx * dx + dy * dy), correctly rounded, as everywhere else. */
typedef struct {
    vf px[CH], py[CH], dt[SMALL][CH], da[SMALL][CH];
} lanes_t;

static inline __attribute__((always_inline)) void lanes_init(
        int64_t N, int64_t M, const float *pos, const float *task, lanes_t *g) {
    const int64_t nc = (N + VL - 1) / VL;
    for (int64_t c = 0; c < nc; c++)
        for (int l = 0; l < VL; l++) {
            const int64_t i = VL * c + l;
            g->px[c][l] = i < N ? pos[2 * i] : 0.0f;
            g->py[c][l] = i < N ? pos[2 * i + 1] : 0.0f;
        }
    for (int64_t j = 0; j < M; j++)
        for (int64_t c = 0; c < nc; c++) {
            const vf dx = task[2 * j] - g->px[c], dy = task[2 * j + 1] - g->py[c];
            g->dt[j][c] = vf_sqrt(dx * dx + dy * dy);
        }
    for (int64_t j = 0; j < N; j++)
        for (int64_t c = 0; c < nc; c++) {
            const vf dx = g->px[c] - pos[2 * j], dy = g->py[c] - pos[2 * j + 1];
            g->da[j][c] = vf_sqrt(dx * dx + dy * dy);
        }
}

/* Scratch of one kernel call: on the stack for small scenes, else on the heap. */
typedef struct {
    float daa_s[SMALL * SMALL], dk_s[SMALL], colmin_s[SMALL];
    int64_t order_s[SMALL], best_s[SMALL], hits_s[SMALL];
    float *daa, *dk, *colmin;
    int64_t *order, *best, *hits;
    void *heap;
} scratch_t;

static int scratch_init(scratch_t *s, int64_t N, int64_t M) {
    const int64_t L = N > M ? N : M;
    s->heap = NULL;
    if (L <= SMALL) {
        s->daa = s->daa_s; s->dk = s->dk_s; s->colmin = s->colmin_s;
        s->order = s->order_s; s->best = s->best_s; s->hits = s->hits_s;
        return 0;
    }
    float *f = malloc(sizeof(float) * (size_t)(N * N + 2 * L) + sizeof(int64_t) * (size_t)(3 * L));
    if (!f) return -1;
    s->heap = f;
    s->daa = f; s->dk = f + N * N; s->colmin = s->dk + L;
    int64_t *g = (int64_t *)(void *)(s->colmin + L);
    s->order = g; s->best = g + L; s->hits = g + 2 * L;
    return 0;
}

/* Calls body(N, M, kt, ka) with compile-time sizes for the paper's scenes (3v3, 6v6), so the
 * small loops unroll, and with the run-time sizes otherwise. */
#define SPECIALIZE(body)                                                                     \
    do {                                                                                     \
        if (N == 3 && M == 3 && kt == 3 && ka == 2) body(3, 3, 3, 2);                        \
        else if (N == 6 && M == 6 && kt == 6 && ka == 5) body(6, 6, 6, 5);                   \
        else body(N, M, kt, ka);                                                             \
    } while (0)

#endif /* AGV_COMMON_H */
