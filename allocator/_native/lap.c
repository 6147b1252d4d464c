/* Shortest augmenting paths for the linear assignment problem, warm-started.
 *
 * The square problem of size m: rows 0..n-1 are real (costs cost[i*m + j]), rows n..m-1 are
 * dummy rows of cost 0 (a rectangular n x m problem, n <= m, padded: a column held by a dummy
 * is a column left free). The state is the dual potentials u (m), v (m) and the partial
 * matching col4row (m), row4col (m), -1 for free. On entry the state must be dual feasible
 * (c[i][j] - u[i] - v[j] >= 0) for every matched row and every column, with every matched
 * pair tight; the potentials of the free rows are arbitrary. Each free row in free_rows is
 * then matched by one Dijkstra search on the reduced costs (the successive shortest path
 * step of Crouse's algorithm, IEEE TAES 2016, which scipy's linear_sum_assignment also uses),
 * which keeps those invariants: at the end the matching is complete and optimal. Infinite
 * costs are forbidden pairs.
 *
 * Returns the number of Dijkstra scans (rows expanded) on success, -1 if some free row has no
 * finite augmenting path (infeasible), -2 if memory ran out.
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

int64_t agv_lap_augment(int64_t n, int64_t m, const double *cost, double *u, double *v,
                        int64_t *col4row, int64_t *row4col, int64_t nfree,
                        const int64_t *free_rows) {
    double *spc = malloc(sizeof(double) * (size_t)(m > 0 ? m : 1));
    int64_t *path = malloc(sizeof(int64_t) * (size_t)(m > 0 ? m : 1));
    int64_t *remaining = malloc(sizeof(int64_t) * (size_t)(m > 0 ? m : 1));
    int64_t *scanned_rows = malloc(sizeof(int64_t) * (size_t)(m > 0 ? m : 1));
    int64_t *scanned_cols = malloc(sizeof(int64_t) * (size_t)(m > 0 ? m : 1));
    int64_t scans = 0;
    if (!spc || !path || !remaining || !scanned_rows || !scanned_cols) {
        free(spc); free(path); free(remaining); free(scanned_rows); free(scanned_cols);
        return -2;
    }
    for (int64_t f = 0; f < nfree; ++f) {
        int64_t cur = free_rows[f];
        if (col4row[cur] >= 0) continue;  /* matched meanwhile: nothing to do */
        for (int64_t j = 0; j < m; ++j) {
            spc[j] = INFINITY;
            path[j] = -1;
            remaining[j] = m - 1 - j;  /* scanned from the end: low columns win ties last */
        }
        int64_t num_remaining = m, nsr = 0, nsc = 0, sink = -1, i = cur;
        double min_val = 0.0;
        while (sink == -1) {
            scanned_rows[nsr++] = i;
            ++scans;
            double lowest = INFINITY;
            int64_t index = -1;
            const double ui = u[i];
            if (i < n) {
                const double *row = cost + i * m;
                for (int64_t it = 0; it < num_remaining; ++it) {
                    int64_t j = remaining[it];
                    double r = min_val + row[j] - ui - v[j];
                    if (r < spc[j]) { path[j] = i; spc[j] = r; }
                    if (spc[j] < lowest || (spc[j] == lowest && row4col[j] == -1)) {
                        lowest = spc[j];
                        index = it;
                    }
                }
            } else {
                for (int64_t it = 0; it < num_remaining; ++it) {
                    int64_t j = remaining[it];
                    double r = min_val - ui - v[j];
                    if (r < spc[j]) { path[j] = i; spc[j] = r; }
                    if (spc[j] < lowest || (spc[j] == lowest && row4col[j] == -1)) {
                        lowest = spc[j];
                        index = it;
                    }
                }
            }
            if (index < 0 || !isfinite(lowest)) {
                free(spc); free(path); free(remaining); free(scanned_rows); free(scanned_cols);
                return -1;
            }
            min_val = lowest;
            int64_t j = remaining[index];
            scanned_cols[nsc++] = j;
            remaining[index] = remaining[--num_remaining];
            if (row4col[j] == -1) sink = j;
            else i = row4col[j];
        }
        u[cur] += min_val;
        for (int64_t k = 1; k < nsr; ++k) {
            int64_t r = scanned_rows[k];
            u[r] += min_val - spc[col4row[r]];
        }
        for (int64_t k = 0; k < nsc; ++k) {
            int64_t c = scanned_cols[k];
            v[c] -= min_val - spc[c];
        }
        int64_t j = sink;
        for (;;) {
            int64_t r = path[j];
            row4col[j] = r;
            int64_t prev = col4row[r];
            col4row[r] = j;
            j = prev;
            if (r == cur) break;
        }
    }
    free(spc); free(path); free(remaining); free(scanned_rows); free(scanned_cols);
    return scans;
}

/* Which entries of the new cost c (n x m) differ from the previous call's (old, n0 x old_m):
 * diff[i*m + j] = 1 where row i and column j both existed (ri[i], cj[j] their old indices,
 * -1 for new ones) and the entry changed; 0 elsewhere. Returns the number of changed entries.
 * One pass, no gather: what the warm start compares. */
int64_t agv_lap_diff(int64_t n, int64_t m, const double *c, int64_t old_m, const double *old,
                     const int64_t *ri, const int64_t *cj, uint8_t *diff) {
    int64_t count = 0;
    for (int64_t i = 0; i < n; ++i) {
        uint8_t *d = diff + i * m;
        const double *row = c + i * m;
        if (ri[i] < 0) {
            for (int64_t j = 0; j < m; ++j) d[j] = 0;
            continue;
        }
        const double *prev = old + ri[i] * old_m;
        for (int64_t j = 0; j < m; ++j) {
            int64_t k = cj[j];
            uint8_t changed = (uint8_t)(k >= 0 && row[j] != prev[k >= 0 ? k : 0]);
            d[j] = changed;
            count += changed;
        }
    }
    return count;
}
