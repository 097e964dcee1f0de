/* wta.cl: streaming winner-take-all over the planes of a (filtered) cost volume.
 *
 * Planes arrive in batches, in increasing plane order; a per-pixel state of WTA_NSTATE floats
 * (layout [field][iw * ih]: field f of pixel k at state[f n + k], the slots WTA_S_<FIELD>) holds
 * what is needed to finish without keeping the volume:
 *   M1 best local-minimum cost, I1 its plane (first one on ties), M1P / M1N the costs of the planes
 *   before / after it, M2 the second-lowest local minimum, PREV / PREV2 the costs of the last two
 *   planes seen, MAX the largest cost seen.
 * Plane j with cost c_j is a local minimum when c_j < c_{j-1} and c_j <= c_{j+1}, where the
 * missing neighbours of the first and last planes count as +infinity (a plateau counts once, at
 * its first plane). The global argmin (first one) is always such a minimum.
 * CLOSING a state, after the last plane n - 1 of its pixel: that plane is tested as a local
 * minimum against +infinity (WTA_BIG), then M2 becomes MAX where no second local minimum was
 * found. A closed state's M1, I1, M1P, M1N and M2 are what the outputs are computed from: here
 * by wta_finalize, for SGM's sums by satsweep.dense.sgm (its own sub-plane fit and confidence
 * scale, on the host).
 *
 * Work sizes: wta_init and wta_finalize have global = (iw, ih), each rounded up to any multiple
 * of the local size; local = any. Work-item (x, y) handles interior pixel (x, y), i.e. tile pixel
 * (mx + x, my + y) of a tile of width tw (the interior excludes the tile's filter margin).
 *   wta_init     : resets the state;
 *   wta_update   : consumes planes plane0 .. plane0 + nb - 1 from cost[nb][th][tw]. Work size:
 *                  global = (ceil(iw / WTA_VEC), ih), rounded up to any multiple; local = any;
 *                  work-item (g, y) handles pixels [g WTA_VEC, (g + 1) WTA_VEC) (clipped to iw)
 *                  of interior row y;
 *   wta_pixel_major : the state after ALL n_planes planes of a pixel-major volume
 *                  cost[i * n_planes + d] (the layout SGM aggregates in), in one pass: equal to
 *                  wta_init then wta_update over planes 0 .. n_planes - 1. Work size: global =
 *                  (ceil(n_pix / WTA_VEC)), rounded up to any multiple; local = any; work-item g
 *                  writes pixels [g WTA_VEC, (g + 1) WTA_VEC) (clipped to n_pix). With
 *                  counted != 0, pixel i has only its first count[i] planes (1 .. n_planes; the
 *                  label counts of sgm.cl's bands), from cost[offset[i]] on (a ragged volume):
 *                  its state is that after those planes.
 *   wta_close    : closes the states of n_pix pixels in place, pixel i after its plane
 *                  n_planes - 1 (with counted != 0, after its plane count[i] - 1):
 *                  wta_pixel_major's states, closed as wta_finalize closes them. Work size: global = (n_pix),
 *                  rounded up to any multiple; local = any; work-item i closes pixel i.
 *   wta_finalize : closes the state after the last of n_planes planes, then: fractional plane
 *                  index (parabola through the best plane and its neighbours, offset clamped to
 *                  [-0.5, 0.5], none at the first and last planes), confidence = (M2 - M1) /
 *                  COST_MAX clamped to [0, 1] (M2 of the closed state: the second-lowest local
 *                  minimum, MAX when there is none), the best cost, and validity: the pixel maps
 *                  into at least one source at the best plane (same rule as sweep.cl) and, when
 *                  reject_edges != 0, the best plane is neither the first nor the last.
 * Compile-time constants: NSRC, CENSUS_RX, CENSUS_RY, AD_WEIGHT and GRAD_WEIGHT (default 0) for
 * COST_MAX; shared with the host (common.h): WTA_BIG, WTA_NSTATE and the slots WTA_S_M1 ..
 * WTA_S_MAX, WTA_VEC (pixels per work-item of wta_update and wta_pixel_major: 8).
 */
#include "common.h"

#if !defined(NSRC) || !defined(CENSUS_RX) || !defined(CENSUS_RY)
#error "NSRC, CENSUS_RX and CENSUS_RY must be defined"
#endif

/* The state's fields are the members of wta_state, one each. */
#if WTA_NSTATE != 8
#error "WTA_NSTATE must be 8 (the fields of wta_state)"
#endif

/* The state of one pixel in private memory, and its moves. */
typedef struct {
    float m1, i1, m1p, m1n, m2, prev, prev2, cmax;
} wta_state;

inline wta_state state_fresh(void)
{
    wta_state st = {WTA_BIG, -1.0f, WTA_BIG, WTA_BIG, WTA_BIG, WTA_BIG, WTA_BIG, -WTA_BIG};
    return st;
}

/* Field f of pixel k lives at state[f n + k] (n pixels). */
inline wta_state state_load(__global const float *state, const size_t n, const size_t k)
{
    wta_state st = {state[WTA_S_M1 * n + k], state[WTA_S_I1 * n + k], state[WTA_S_M1P * n + k],
                    state[WTA_S_M1N * n + k], state[WTA_S_M2 * n + k], state[WTA_S_PREV * n + k],
                    state[WTA_S_PREV2 * n + k], state[WTA_S_MAX * n + k]};
    return st;
}

inline void state_store(__global float *state, const size_t n, const size_t k, const wta_state st)
{
    state[WTA_S_M1 * n + k] = st.m1;
    state[WTA_S_I1 * n + k] = st.i1;
    state[WTA_S_M1P * n + k] = st.m1p;
    state[WTA_S_M1N * n + k] = st.m1n;
    state[WTA_S_M2 * n + k] = st.m2;
    state[WTA_S_PREV * n + k] = st.prev;
    state[WTA_S_PREV2 * n + k] = st.prev2;
    state[WTA_S_MAX * n + k] = st.cmax;
}

/* Plane j (cost cj, neighbours cjm, cjp) is tested as a local minimum and merged in the state. */
inline void consider(const int j, const float cjm, const float cj, const float cjp, wta_state *st)
{
    if (!(cj < cjm && cj <= cjp)) return;
    if (cj < st->m1) {
        st->m2 = st->m1;
        st->m1 = cj;
        st->i1 = (float)j;
        st->m1p = cjm;
        st->m1n = cjp;
    } else if (cj < st->m2) {
        st->m2 = cj;
    }
}

/* Plane p with cost c arrives: plane p - 1 can now be tested (its neighbours are known). */
inline void state_push(wta_state *st, const int p, const float c)
{
    if (p >= 1) consider(p - 1, st->prev2, st->prev, c, st);
    st->prev2 = st->prev;
    st->prev = c;
    st->cmax = fmax(st->cmax, c);
}

/* Close the state after the last plane n - 1 of its pixel (see the header): that plane tested as
 * a local minimum against +infinity, then M2 = MAX where there is no second local minimum. */
inline void state_close(wta_state *st, const int n)
{
    consider(n - 1, st->prev2, st->prev, WTA_BIG, st);
    if (!(st->m2 < WTA_BIG)) st->m2 = st->cmax;
}

__kernel void wta_init(__global float *state, const int iw, const int ih)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= iw || y >= ih) return;
    state_store(state, (size_t)iw * ih, IDX2(x, y, iw), state_fresh());
}

/* wta_update and wta_pixel_major run WTA_VEC (8) adjacent pixels per work-item with the state in
 * float8 and the branches of consider() as selects (PoCL leaves the one-pixel form scalar); the
 * comparisons are the same, so the states are the same bit for bit. The last, narrower group
 * runs the one-pixel form. */
#if WTA_VEC != 8
#error "WTA_VEC must be 8 (the vector kernels use float8)"
#endif

typedef struct {
    float8 m1, i1, m1p, m1n, m2, prev, prev2, cmax;
} wta_state8;

inline wta_state8 state_load8(__global const float *state, const size_t n, const size_t k)
{
    wta_state8 st = {vload8(0, state + WTA_S_M1 * n + k), vload8(0, state + WTA_S_I1 * n + k),
                     vload8(0, state + WTA_S_M1P * n + k), vload8(0, state + WTA_S_M1N * n + k),
                     vload8(0, state + WTA_S_M2 * n + k), vload8(0, state + WTA_S_PREV * n + k),
                     vload8(0, state + WTA_S_PREV2 * n + k), vload8(0, state + WTA_S_MAX * n + k)};
    return st;
}

inline void state_store8(__global float *state, const size_t n, const size_t k,
                         const wta_state8 st)
{
    vstore8(st.m1, 0, state + WTA_S_M1 * n + k);
    vstore8(st.i1, 0, state + WTA_S_I1 * n + k);
    vstore8(st.m1p, 0, state + WTA_S_M1P * n + k);
    vstore8(st.m1n, 0, state + WTA_S_M1N * n + k);
    vstore8(st.m2, 0, state + WTA_S_M2 * n + k);
    vstore8(st.prev, 0, state + WTA_S_PREV * n + k);
    vstore8(st.prev2, 0, state + WTA_S_PREV2 * n + k);
    vstore8(st.cmax, 0, state + WTA_S_MAX * n + k);
}

/* consider() and state_push(), lane by lane. */
inline void consider8(const int j, const float8 cjm, const float8 cj, const float8 cjp,
                      wta_state8 *st)
{
    const int8 is_min = (cj < cjm) & (cj <= cjp);
    const int8 better = is_min & (cj < st->m1);
    const int8 second = is_min & ~better & (cj < st->m2);
    st->m2 = select(select(st->m2, cj, second), st->m1, better);
    st->m1 = select(st->m1, cj, better);
    st->i1 = select(st->i1, (float8)(float)j, better);
    st->m1p = select(st->m1p, cjm, better);
    st->m1n = select(st->m1n, cjp, better);
}

inline void state_push8(wta_state8 *st, const int p, const float8 c)
{
    if (p >= 1) consider8(p - 1, st->prev2, st->prev, c, st);
    st->prev2 = st->prev;
    st->prev = c;
    st->cmax = fmax(st->cmax, c);
}

__kernel void wta_update(__global const float *cost, const int tw, const int th, const int mx,
                         const int my, const int iw, const int ih, const int nb,
                         const int plane0, __global float *state)
{
    const int x0 = get_global_id(0) * WTA_VEC, y = get_global_id(1);
    if (x0 >= iw || y >= ih) return;
    const size_t n = (size_t)iw * ih, plane = (size_t)tw * th;
    if (x0 + WTA_VEC > iw) {
        for (int x = x0; x < iw; ++x) {
            const size_t k = IDX2(x, y, iw), pix = IDX2(mx + x, my + y, tw);
            wta_state st = state_load(state, n, k);
            for (int b = 0; b < nb; ++b) state_push(&st, plane0 + b, cost[b * plane + pix]);
            state_store(state, n, k, st);
        }
        return;
    }
    const size_t k = IDX2(x0, y, iw), pix = IDX2(mx + x0, my + y, tw);
    wta_state8 st = state_load8(state, n, k);
    for (int b = 0; b < nb; ++b) state_push8(&st, plane0 + b, vload8(0, cost + b * plane + pix));
    state_store8(state, n, k, st);
}

/* state_push8 on the lanes where `on` is set; the others keep their state. */
inline void state_push8_lanes(wta_state8 *st, const int p, const float8 c, const int8 on)
{
    wta_state8 t = *st;
    state_push8(&t, p, c);
    st->m1 = select(st->m1, t.m1, on);
    st->i1 = select(st->i1, t.i1, on);
    st->m1p = select(st->m1p, t.m1p, on);
    st->m1n = select(st->m1n, t.m1n, on);
    st->m2 = select(st->m2, t.m2, on);
    st->prev = select(st->prev, t.prev, on);
    st->prev2 = select(st->prev2, t.prev2, on);
    st->cmax = select(st->cmax, t.cmax, on);
}

__kernel void wta_pixel_major(__global const float *cost, const int n_pix, const int n_planes,
                              __global const int *count, __global const ulong *offset,
                              const int counted, __global float *state)
{
    const int i0 = get_global_id(0) * WTA_VEC;
    if (i0 >= n_pix) return;
    if (i0 + WTA_VEC > n_pix) {
        for (int i = i0; i < n_pix; ++i) {
            wta_state st = state_fresh();
            __global const float *c = cost + (counted ? offset[i] : (size_t)i * n_planes);
            const int n = counted ? count[i] : n_planes;
            for (int p = 0; p < n; ++p) state_push(&st, p, c[p]);
            state_store(state, (size_t)n_pix, i, st);
        }
        return;
    }
    const wta_state one = state_fresh();
    wta_state8 st = {(float8)one.m1, (float8)one.i1, (float8)one.m1p, (float8)one.m1n,
                     (float8)one.m2, (float8)one.prev, (float8)one.prev2, (float8)one.cmax};
    const int8 n8 = counted ? vload8(0, count + i0) : (int8)(n_planes);
    const int4 lo4 = min(n8.lo, n8.hi), hi4 = max(n8.lo, n8.hi);
    const int2 lo2 = min(lo4.lo, lo4.hi), hi2 = max(hi4.lo, hi4.hi);
    const int n_all = min(lo2.x, lo2.y);  /* planes every lane has */
    const int n_any = max(hi2.x, hi2.y);  /* planes some lane has */
    /* the 8 pixels' labels; a lane past its count rereads its last label (inside the volume,
     * which a ragged one may end right after) and ignores it */
    __global const float *c0, *c1, *c2, *c3, *c4, *c5, *c6, *c7;
    if (counted) {
        c0 = cost + offset[i0]; c1 = cost + offset[i0 + 1]; c2 = cost + offset[i0 + 2];
        c3 = cost + offset[i0 + 3]; c4 = cost + offset[i0 + 4]; c5 = cost + offset[i0 + 5];
        c6 = cost + offset[i0 + 6]; c7 = cost + offset[i0 + 7];
    } else {
        const size_t d = (size_t)n_planes;
        c0 = cost + (size_t)i0 * d; c1 = c0 + d; c2 = c1 + d; c3 = c2 + d; c4 = c3 + d;
        c5 = c4 + d; c6 = c5 + d; c7 = c6 + d;
    }
    int p = 0;
    for (; p < n_all; ++p)
        state_push8(&st, p, (float8)(c0[p], c1[p], c2[p], c3[p], c4[p], c5[p], c6[p], c7[p]));
    for (; p < n_any; ++p) {
        const int8 q = min((int8)(p), n8 - 1);
        state_push8_lanes(&st, p, (float8)(c0[q.s0], c1[q.s1], c2[q.s2], c3[q.s3], c4[q.s4],
                                           c5[q.s5], c6[q.s6], c7[q.s7]), (int8)(p) < n8);
    }
    state_store8(state, (size_t)n_pix, i0, st);
}

__kernel void wta_close(__global float *state, const int n_pix, const int n_planes,
                        __global const int *count, const int counted)
{
    const int i = get_global_id(0);
    if (i >= n_pix) return;
    wta_state st = state_load(state, (size_t)n_pix, i);
    state_close(&st, counted ? count[i] : n_planes);
    state_store(state, (size_t)n_pix, i, st);
}

__kernel void wta_finalize(__global const float *state, const int iw, const int ih,
                           const int n_planes, const int mx, const int my,
                           __global const float *homography, __global const int *src_size,
                           const int reject_edges, __global float *plane_index,
                           __global float *confidence, __global float *best_cost,
                           __global uchar *valid)
{
    const int x = get_global_id(0), y = get_global_id(1);
    if (x >= iw || y >= ih) return;
    const size_t n = (size_t)iw * ih, k = IDX2(x, y, iw);
    wta_state st = state_load(state, n, k);
    state_close(&st, n_planes);
    const float m1 = st.m1, m1p = st.m1p, m1n = st.m1n, c2 = st.m2;
    const int ib = (int)st.i1;
    float offset = 0.0f;
    if (ib > 0 && ib < n_planes - 1) {
        const float denom = m1p - 2.0f * m1 + m1n;
        if (denom > 0.0f) offset = fmin(fmax(0.5f * (m1p - m1n) / denom, -0.5f), 0.5f);
    }
    int ok = 0;
    for (int s = 0; s < NSRC; ++s) {
        float u, v;
        __global const float *H = homography + (ib * NSRC + s) * 9;
        if (apply_homography(H, (float)(mx + x), (float)(my + y), &u, &v)
            && u >= 0.0f && u <= (float)(src_size[2 * s] - 1)
            && v >= 0.0f && v <= (float)(src_size[2 * s + 1] - 1))
            ok = 1;
    }
    if (reject_edges && (ib == 0 || ib == n_planes - 1)) ok = 0;
    plane_index[k] = (float)ib + offset;
    confidence[k] = fmin(fmax((c2 - m1) / COST_MAX, 0.0f), 1.0f);
    best_cost[k] = m1;
    valid[k] = (uchar)ok;
}
