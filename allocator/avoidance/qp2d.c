/* The exact 2-D velocity QP of every AGV and its least-violation fallback, one AGV at a time.
 *
 * The C twin of allocator/avoidance/exact_qp.py (solve_qp_2d) and least_violation.py
 * (least_violation_2d): the same candidates, the same KKT filters and the same tolerances, so
 * both give the same velocities (tests/allocator/avoidance/test_native_qp.py checks it against
 * them, OSQP and cvxpy). Built on first use by allocator/avoidance/native.py.
 *
 * Per AGV i: min |v - p|^2 s.t. lower <= A v <= upper (rows of R slots, infinite bounds where
 * absent). The rows are rewritten one-sided with unit normals, g . v <= h (a lower bound
 * becomes -a . v <= -lower, hard). The optimum is p, p projected on one violated line, or a
 * vertex of a violated line with another line (KKT multipliers >= 0); the feasible candidate
 * nearest p is the optimum. If no candidate is feasible, the rows conflict and the AGV gets the
 * ORCA "3-D" program: min t + (r / 2) |v - p|^2 s.t. g . v - w t <= h on soft rows (w > 0),
 * g . v <= h on hard rows, t >= 0; its optimum is one of the candidates enumerated in
 * least_violation_2d (at most three active constraints, one of them soft).
 */
#include <math.h>
#include <stdint.h>
#include <stdlib.h>

typedef struct {
    double gx, gy, h, w; /* unit normal, bound, fallback weight / |a| (0: hard) */
} Row;

/* One AGV's one-sided rows; returns their number. */
static int collect(const double *A, const double *lo, const double *hi, const double *weight,
                   int R, Row *rows)
{
    int m = 0;
    for (int k = 0; k < R; k++) {
        double ax = A[2 * k], ay = A[2 * k + 1];
        double nrm = sqrt(ax * ax + ay * ay);
        for (int side = 0; side < 2; side++) {
            double b = side ? -lo[k] : hi[k];
            if (isnan(b) || b == INFINITY)
                continue;
            double sg = side ? -1.0 : 1.0, w = side ? 0.0 : weight[k];
            if (nrm < 1e-12) {
                if (b >= 0.0)
                    continue; /* a zero row that holds anyway */
                rows[m].gx = 0.0;
                rows[m].gy = 0.0;
                rows[m].h = b; /* can never hold */
                rows[m].w = w;
                m++;
                continue;
            }
            double inv = 1.0 / nrm;
            rows[m].gx = sg * ax * inv;
            rows[m].gy = sg * ay * inv;
            rows[m].h = b * inv;
            rows[m].w = w * inv;
            m++;
        }
    }
    return m;
}

/* The exact QP; returns 1 when feasible (velocity in v), 0 when the rows conflict. */
static int solve_qp(const Row *r, int m, double px, double py, double tol, double *s,
                    double *v)
{
    int any = 0;
    for (int k = 0; k < m; k++) {
        s[k] = r[k].gx * px + r[k].gy * py - r[k].h;
        any |= s[k] > tol;
    }
    v[0] = px;
    v[1] = py;
    if (!any)
        return 1;
    /* 1. projections on the violated lines: the nearest feasible one */
    int bk = -1;
    double best = INFINITY;
    for (int k = 0; k < m; k++) {
        if (!(s[k] > tol) || !(s[k] < best))
            continue;
        int ok = 1;
        for (int j = 0; j < m && ok; j++)
            ok = s[j] - s[k] * (r[j].gx * r[k].gx + r[j].gy * r[k].gy) <= tol;
        if (ok) {
            best = s[k];
            bk = k;
        }
    }
    if (bk >= 0) {
        v[0] = px - s[bk] * r[bk].gx;
        v[1] = py - s[bk] * r[bk].gy;
        return 1;
    }
    /* 2. vertices of a violated line with any other line, KKT multipliers >= 0 */
    best = INFINITY;
    int found = 0;
    for (int j = 0; j < m; j++) {
        if (!(s[j] > tol))
            continue;
        double gjx = r[j].gx, gjy = r[j].gy, hj = r[j].h;
        for (int k = 0; k < m; k++) {
            double gkx = r[k].gx, gky = r[k].gy, hk = r[k].h;
            double det = gjx * gky - gjy * gkx;
            if (!(fabs(det) > 1e-12))
                continue;
            double inv = 1.0 / det;
            double cx = (hj * gky - hk * gjy) * inv, cy = (gjx * hk - gkx * hj) * inv;
            double dx = px - cx, dy = py - cy;
            double lj = (dx * gky - dy * gkx) * inv, lk = (gjx * dy - gjy * dx) * inv;
            if (!(lj >= -1e-6 && lk >= -1e-6))
                continue;
            double d2 = dx * dx + dy * dy;
            if (!(d2 < best))
                continue;
            int ok = 1;
            for (int l = 0; l < m && ok; l++)
                ok = r[l].gx * cx + r[l].gy * cy - r[l].h <= tol;
            if (ok) {
                best = d2;
                v[0] = cx;
                v[1] = cy;
                found = 1;
            }
        }
    }
    if (!found) {
        v[0] = px;
        v[1] = py;
    }
    return found;
}

typedef struct {
    const double *ux, *uy, *c; /* scaled soft rows: u . v - c */
    const double *hx, *hy, *hh; /* hard rows */
    int ks, kh;
    double px, py, reg, tol;
    double best, bx, by, bt;
} LV;

static void consider(LV *q, double x, double y)
{
    if (!isfinite(x) || !isfinite(y))
        return;
    for (int l = 0; l < q->kh; l++)
        if (!(q->hx[l] * x + q->hy[l] * y - q->hh[l] <= q->tol))
            return;
    double t = 0.0;
    for (int k = 0; k < q->ks; k++) {
        double e = q->ux[k] * x + q->uy[k] * y - q->c[k];
        if (e > t)
            t = e;
    }
    double dx = x - q->px, dy = y - q->py;
    double f = t + 0.5 * q->reg * (dx * dx + dy * dy);
    if (f < q->best) {
        q->best = f;
        q->bx = x;
        q->by = y;
        q->bt = t;
    }
}

/* Intersection of n1 . v = d1 and n2 . v = d2 (least_violation._intersect). */
static int intersect(double n1x, double n1y, double d1, double n2x, double n2y, double d2,
                     double *x, double *y)
{
    double det = n1x * n2y - n1y * n2x;
    double scale = sqrt((n1x * n1x + n1y * n1y) * (n2x * n2x + n2y * n2y));
    if (!(fabs(det) > 1e-10 * scale) || !(scale > 0) || !isfinite(d1) || !isfinite(d2))
        return 0;
    double inv = 1.0 / det;
    *x = (d1 * n2y - d2 * n1y) * inv;
    *y = (n1x * d2 - n2x * d1) * inv;
    return 1;
}

/* alpha a + beta b = r (least_violation._solve2). */
static int solve2(double ax, double ay, double bx, double by, double rx, double ry,
                  double *alpha, double *beta)
{
    double det = ax * by - ay * bx;
    if (!(fabs(det) > 1e-14))
        return 0;
    double inv = 1.0 / det;
    *alpha = (rx * by - ry * bx) * inv;
    *beta = (ax * ry - ay * rx) * inv;
    return 1;
}

/* Projection of q on n . v = d (least_violation._project). */
static int project(double qx, double qy, double nx, double ny, double d, double *x, double *y)
{
    double nn = nx * nx + ny * ny;
    if (!(nn > 1e-20) || !isfinite(d) || !isfinite(qx) || !isfinite(qy))
        return 0;
    double f = (nx * qx + ny * qy - d) / nn;
    *x = qx - f * nx;
    *y = qy - f * ny;
    return 1;
}

/* The least-violation program; returns t (inf where even the hard rows conflict). */
static double least_violation(const Row *r, int m, double px, double py, double reg,
                              double tol, double *buf, double *v)
{
    double *ux = buf, *uy = buf + m, *c = buf + 2 * m;
    double *hx = buf + 3 * m, *hy = buf + 4 * m, *hh = buf + 5 * m;
    int ks = 0, kh = 0;
    for (int k = 0; k < m; k++) {
        if (r[k].w > 0) {
            ux[ks] = r[k].gx / r[k].w;
            uy[ks] = r[k].gy / r[k].w;
            c[ks] = r[k].h / r[k].w;
            ks++;
        } else {
            hx[kh] = r[k].gx;
            hy[kh] = r[k].gy;
            hh[kh] = r[k].h;
            kh++;
        }
    }
    LV q = {ux, uy, c, hx, hy, hh, ks, kh, px, py, reg, tol, INFINITY, 0.0, 0.0, INFINITY};
    const double neg = -1e-7;
    double x, y, mu, nu, mk, ml;
    for (int k = 0; k < ks; k++) { /* one soft row, and its point projected on a hard line */
        double qx = px - ux[k] / reg, qy = py - uy[k] / reg;
        consider(&q, qx, qy);
        for (int l = 0; l < kh; l++) {
            if (!project(qx, qy, hx[l], hy[l], hh[l], &x, &y))
                continue;
            nu = (reg * (px - x) - ux[k]) * hx[l] + (reg * (py - y) - uy[k]) * hy[l];
            if (nu >= neg)
                consider(&q, x, y);
        }
    }
    for (int a = 0; a < kh; a++) /* hard vertices */
        for (int b = a + 1; b < kh; b++)
            if (intersect(hx[a], hy[a], hh[a], hx[b], hy[b], hh[b], &x, &y))
                consider(&q, x, y);
    for (int j = 0; j < ks; j++) {
        double qjx = px - ux[j] / reg, qjy = py - uy[j] / reg;
        for (int k = j + 1; k < ks; k++) { /* two soft rows tie */
            double tx = ux[j] - ux[k], ty = uy[j] - uy[k], td = c[j] - c[k];
            if (project(qjx, qjy, tx, ty, td, &x, &y)) {
                mu = ((reg * (px - x) - ux[k]) * tx + (reg * (py - y) - uy[k]) * ty)
                    / (tx * tx + ty * ty);
                if (mu >= neg && mu <= 1 - neg)
                    consider(&q, x, y);
            }
            for (int l = 0; l < kh; l++) { /* ... on a hard line */
                if (!intersect(tx, ty, td, hx[l], hy[l], hh[l], &x, &y))
                    continue;
                double rx = reg * (px - x) - ux[k], ry = reg * (py - y) - uy[k];
                if (solve2(tx, ty, hx[l], hy[l], rx, ry, &mu, &nu) && mu >= neg
                    && mu <= 1 - neg && nu >= neg)
                    consider(&q, x, y);
            }
            for (int l = k + 1; l < ks; l++) { /* three soft rows tie */
                if (!intersect(ux[j] - ux[k], uy[j] - uy[k], c[j] - c[k], ux[j] - ux[l],
                               uy[j] - uy[l], c[j] - c[l], &x, &y))
                    continue;
                if (solve2(ux[k] - ux[j], uy[k] - uy[j], ux[l] - ux[j], uy[l] - uy[j],
                           reg * (px - x) - ux[j], reg * (py - y) - uy[j], &mk, &ml)
                    && mk >= neg && ml >= neg && mk + ml <= 1 - neg)
                    consider(&q, x, y);
            }
        }
    }
    if (q.best == INFINITY) {
        v[0] = 0.0;
        v[1] = 0.0;
        return INFINITY;
    }
    v[0] = q.bx;
    v[1] = q.by;
    return q.bt;
}

/* Every AGV's velocity (n, 2); fell[i] = 1 where its rows conflicted and its least violation
 * exceeds fallback_tol (violation[i] = that t, else 0). Inactive AGVs get 0. Returns the
 * number of AGVs that fell back, or -1 if memory ran out. */
int64_t agv_velocity_qp(int64_t n, int64_t R, const double *A, const double *lower,
                        const double *upper, const double *preferred, const uint8_t *active,
                        const double *weight, double regularization, double tol,
                        double fallback_tol, double *velocity, uint8_t *fell,
                        double *violation)
{
    Row *rows = malloc(sizeof(Row) * (size_t)(2 * R + 1));
    double *buf = malloc(sizeof(double) * (size_t)(12 * R + 6));
    if (!rows || !buf) {
        free(rows);
        free(buf);
        return -1;
    }
    int64_t count = 0;
    for (int64_t i = 0; i < n; i++) {
        double *v = velocity + 2 * i;
        fell[i] = 0;
        violation[i] = 0.0;
        if (!active[i]) {
            v[0] = 0.0;
            v[1] = 0.0;
            continue;
        }
        int m = collect(A + 2 * R * i, lower + R * i, upper + R * i, weight, (int)R, rows);
        double px = preferred[2 * i], py = preferred[2 * i + 1];
        if (solve_qp(rows, m, px, py, tol, buf, v))
            continue;
        double t = least_violation(rows, m, px, py, regularization, tol, buf, v);
        if (t > fallback_tol) {
            fell[i] = 1;
            violation[i] = t;
            count++;
        }
    }
    free(rows);
    free(buf);
    return count;
}
