/* Fused CPU kernels of the AGV simulator (see sim/native.py, which builds and loads them).
 *
 * Each kernel loops over the B environments in C and does, per environment, what the torch
 * reference in sim/ does with some forty batched tensor operations. The torch code stays the
 * definition; tests/sim/test_native.py checks both agree.
 *
 * Layouts are torch's contiguous row-major ones: positions (B, N, 2) float32, bool tensors as
 * one byte per entry, indices int64. Nothing here allocates per environment.
 *
 * One translation unit: the concept files below are included here, so that the compiler
 * inlines across them (the fused step calls the pair pass, the claim rule and the
 * observations of every environment in one loop). Each file names its torch reference.
 */
#include "common.h"
#include "observations.h"
#include "physics.h"
#include "tasks.h"
#include "lifelong.h"
#include "shelves.h"
#include "orders.h"
#include "streams.h"

#include "step.c"
#include "ipf.c"
#include "spawn.c"
