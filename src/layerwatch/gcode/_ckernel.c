/* Ahead-of-time compiled G-code kernel: the same state machine as kernel.py + lexer.py + arcs.py.
 *
 * Built by setup.py at install (an optional extension: without a compiler the numba kernel is
 * used). It must give the numba kernel's outputs bit for bit; tests/gcode/test_native_kernel.py
 * runs both on every shared corpus file and on the fuzz seeds. The slots and layouts below are
 * those of kernel_abi.py (the module exposes them as ABI for that test to compare).
 *
 * run(buf, probes, chord_tol, e_rel_init, e_area_init) -> 11 bytearrays, the segments planar:
 *   start (S x 2 float64), end (S x 2 float64), z (S float64), e (S float64), line (S int64),
 *   tool (S uint8), travel_line (T int64), cmt (C x 2 int64), probe_state (P x 13 float64),
 *   stats (22 int64), fstats (5 float64). The numba kernel's segf is (start, end, z, e)
 *   side by side and its segi (line, tool).
 * Build with -ffp-contract=off: a fused multiply-add would round differently from numba.
 */
#define PY_SSIZE_T_CLEAN
#include <Python.h>
#include <math.h>
#include <stdint.h>
#include <string.h>

#ifndef LW_SOURCE_KEY
#define LW_SOURCE_KEY "unknown"
#endif

/* ---- lexer (lexer.py) */
#define NL 10
#define CR 13
#define TAB 9
#define SPACE 32
#define BAD_BYTES 1
#define BAD_WORD 2
#define MAX_G 4
enum { W_A = 0, W_D = 3, W_E = 4, W_F = 5, W_G = 6, W_I = 8, W_J = 9, W_M = 12, W_R = 17, W_S = 18,
       W_T = 19, W_X = 23, W_Y = 24, W_Z = 25, N_WORDS = 26 };
#define HAS(w) ((has >> (w)) & 1u)

/* ---- kernel (kernel_abi.py) */
enum { ST_LINES, ST_SEG, ST_TRAVEL, ST_CMT, ST_BAD, ST_FIRST_BAD, ST_UNKNOWN, ST_ABSURD, ST_FIRST_ABSURD,
       ST_TOOLON, ST_ARCS, ST_ARC_BAD, ST_FIRST_ARC_BAD, ST_NONL, ST_FWRETRACT, ST_VOLUMETRIC,
       ST_ARC_CAPPED, ST_FIRST_ARC_CAPPED, ST_FLOW_SET, ST_MALFORMED, ST_FIRST_MALFORMED, N_STATS = 22 };
enum { FS_XY_CMD, FS_CMD_HIGH, FS_FED_HIGH, FS_EONLY_FED, FS_XY_FED, N_FSTATS };
enum { MS_LX, MS_LY, MS_LZ, MS_OX, MS_OY, MS_OZ, MS_E, MS_FEED, MS_ABS, MS_EREL, MS_SCALE, MS_TOOL,
       MS_TOOLON, MS_TOOLON_MODE, MS_MOTION, MS_EAREA, MS_CMD, MS_CMD_HIGH, MS_FED, MS_FED_HIGH,
       MS_ARC_CHORDS, MS_ARC_BUDGET, MS_FLOW = 24, N_TOOLS = 16, N_MS = 40 };
#define N_PROBE 13
#define ABSURD_MM 1.0e5
#define ARC_MAX_CHORDS 2048
#define ARC_BUDGET_BASE 200000
#define ARC_BUDGET_PER_BYTE 8
#define ARC_MIN_CHORD_MM 0.02
enum { ACT_NONE, ACT_HOME, ACT_SETPOS, ACT_MOVE };

static double POW10[309];
static unsigned char TAG_FIRST[256];

static inline int is_digit(unsigned c) { return c - '0' < 10u; }
static inline int is_letter(unsigned c) { return (c - 'A' < 26u) || (c - 'a' < 26u); }

/* parse_num: decimal number, no exponent; integer mantissa scaled once by a power of ten */
static inline Py_ssize_t parse_num(const unsigned char *buf, Py_ssize_t i, Py_ssize_t n, double *out, int *ok)
{
    while (i < n && (buf[i] == SPACE || buf[i] == TAB)) i++;
    int neg = 0;
    if (i < n && (buf[i] == '-' || buf[i] == '+')) { neg = buf[i] == '-'; i++; }
    int64_t mant = 0;
    int nd = 0, exp10 = 0;
    Py_ssize_t i0 = i;
    while (i < n && is_digit(buf[i])) {
        if (nd < 18) { mant = mant * 10 + (buf[i] - '0'); nd += mant > 0; }
        else exp10++;
        i++;
    }
    *ok = i > i0;
    if (i < n && buf[i] == '.') {
        i++;
        while (i < n && is_digit(buf[i])) {
            if (nd < 18) { mant = mant * 10 + (buf[i] - '0'); nd += mant > 0; exp10--; }
            i++;
            *ok = 1;
        }
    }
    double val = (double)mant;
    if (exp10 < 0) val /= POW10[-exp10 < 308 ? -exp10 : 308];
    else if (exp10 > 0) val *= POW10[exp10 < 308 ? exp10 : 308];
    *out = neg ? -val : val;
    return i;
}

static inline Py_ssize_t to_eol(const unsigned char *buf, Py_ssize_t i, Py_ssize_t n)
{
    const unsigned char *p = memchr(buf + i, NL, (size_t)(n - i));
    return p ? (Py_ssize_t)(p - buf) : n;
}

typedef struct {
    double val[N_WORDS];
    uint32_t has;
    double g[MAX_G];
    int ng, mcode, bad, extended;
    Py_ssize_t cmt_at;
} Words;

/* lex_line: one line from buf[i] into w; returns the index of its newline (or n) */
static inline Py_ssize_t lex_line(const unsigned char *buf, Py_ssize_t i, Py_ssize_t n, Words *w)
{
    uint32_t has = 0;
    int first = 1;
    w->ng = 0; w->mcode = -1; w->cmt_at = -1; w->bad = 0; w->extended = 0;
    while (i < n && buf[i] != NL) {
        unsigned c = buf[i];
        if (c == ';') {
            Py_ssize_t j = i + 1;
            while (j < n && (buf[j] == SPACE || buf[j] == TAB)) j++;
            if (j < n && TAG_FIRST[buf[j]]) w->cmt_at = i;
            w->has = has;
            return to_eol(buf, i, n);
        }
        if (c == '(') {
            int depth = 0;
            while (i < n && buf[i] != NL) {
                depth += buf[i] == '(' ? 1 : (buf[i] == ')' ? -1 : 0);
                i++;
                if (depth == 0) break;
            }
            continue;
        }
        if (c == SPACE || c == TAB || c == CR) { i++; continue; }
        if (c == '*') { w->has = has; return to_eol(buf, i, n); }
        if (is_letter(c)) {
            if (first && i + 1 < n && (is_letter(buf[i + 1]) || buf[i + 1] == '_')) {
                w->ng = 0; w->mcode = -1; w->extended = 1; w->has = has;
                return to_eol(buf, i, n);
            }
            first = 0;
            int wd = (int)(c & ~32u) - 'A';
            double v;
            int ok;
            i = parse_num(buf, i + 1, n, &v, &ok);
            if (wd == W_G && ok) {
                if (w->ng < MAX_G) w->g[w->ng++] = v;
            } else if (wd == W_M && ok) {
                if (w->mcode < 0) {
                    w->mcode = (0 <= v && v < 1e6) ? (int)v : 99999;
                    int m = w->mcode;
                    if (!(m == 82 || m == 83 || m == 101 || m == 103 || m == 200 || m == 221))
                        while (i < n && buf[i] != NL && buf[i] != ';') i++;
                }
            } else {
                has |= 1u << wd;
                w->val[wd] = ok ? v : NAN;
            }
            continue;
        }
        w->bad |= (c >= 128 || c < 32) ? BAD_BYTES : BAD_WORD;
        i++;
    }
    w->has = has;
    return i;
}

/* ---- growable outputs: bytearrays resized by doubling, shrunk to size at the end */
typedef struct { PyObject *ba; Py_ssize_t cap, n, width; } Out;

static int out_init(Out *o, Py_ssize_t cap, Py_ssize_t width)
{
    o->ba = PyByteArray_FromStringAndSize(NULL, cap * width);
    o->cap = cap; o->n = 0; o->width = width;
    return o->ba ? 0 : -1;
}

static int out_reserve(Out *o, Py_ssize_t more)
{
    if (o->n + more <= o->cap) return 0;
    Py_ssize_t cap = o->cap * 2 + more + 16;
    if (PyByteArray_Resize(o->ba, cap * o->width) < 0) return -1;
    o->cap = cap;
    return 0;
}

#define OUT_PTR(o, type) ((type *)PyByteArray_AS_STRING((o)->ba))

/* the segment columns grow together: seg[SEG_A].n is the segment count */
enum { SEG_A, SEG_B, SEG_Z, SEG_E, SEG_LINE, SEG_TOOL, N_SEG };
static const Py_ssize_t SEG_WIDTH[N_SEG] = {16, 16, 8, 8, 8, 1};

typedef struct {
    double ms[N_MS];
    int64_t stats[N_STATS];
    double fs[N_FSTATS];
    Out seg[N_SEG], travel, cmt;
    double chord_tol;
} Machine;

static inline void flag(int64_t *stats, int count_slot, int first_slot, int64_t line)
{
    if (stats[count_slot] == 0) stats[first_slot] = line;
    stats[count_slot]++;
}

static inline int push_seg(Machine *m, double x0, double y0, double x1, double y1, double z, double e,
                           int64_t line, int64_t tool)
{
    Py_ssize_t s = m->seg[SEG_A].n;
    if (s >= m->seg[SEG_A].cap)
        for (int c = 0; c < N_SEG; c++)
            if (out_reserve(&m->seg[c], 1) < 0) return -1;
    double *a = OUT_PTR(&m->seg[SEG_A], double) + 2 * s, *b = OUT_PTR(&m->seg[SEG_B], double) + 2 * s;
    a[0] = x0; a[1] = y0; b[0] = x1; b[1] = y1;
    OUT_PTR(&m->seg[SEG_Z], double)[s] = z;
    OUT_PTR(&m->seg[SEG_E], double)[s] = e;
    OUT_PTR(&m->seg[SEG_LINE], int64_t)[s] = line;
    OUT_PTR(&m->seg[SEG_TOOL], uint8_t)[s] = (uint8_t)tool;
    for (int c = 0; c < N_SEG; c++) m->seg[c].n = s + 1;
    return 0;
}

/* _apply_g: returns the action; *mo the motion (-1 none), *nonmotion set for G4, G10 ... */
static inline int apply_g(Machine *m, double g, int *mo, int *nonmotion)
{
    double *ms = m->ms;
    long long gi = (0 <= g && g < 1e6) ? (long long)(g + 1e-6) : 9999;
    *mo = -1;
    if (gi <= 3 && fabs(g - (double)gi) < 1e-6) { ms[MS_MOTION] = (double)gi; *mo = (int)gi; return ACT_MOVE; }
    switch (gi) {
    case 90: ms[MS_ABS] = 1.0; break;
    case 91: ms[MS_ABS] = 0.0; break;
    case 20: ms[MS_SCALE] = 25.4; break;
    case 21: ms[MS_SCALE] = 1.0; break;
    case 28: return ACT_HOME;
    case 92: return ACT_SETPOS;
    case 10: case 11: m->stats[ST_FWRETRACT]++; *nonmotion = 1; return ACT_NONE;
    case 17: case 94: break;
    default:
        if (!(gi == 4 || gi == 29 || gi == 53 || gi == 40 || gi == 80)) m->stats[ST_UNKNOWN]++;
        *nonmotion = 1;
        return ACT_NONE;
    }
    return ACT_NONE;
}

static void apply_m(Machine *m, int code, const Words *w)
{
    double *ms = m->ms;
    uint32_t has = w->has;
    if (code == 82) ms[MS_EREL] = 0.0;
    else if (code == 83) ms[MS_EREL] = 1.0;
    else if (code == 101) { ms[MS_TOOLON] = 1.0; ms[MS_TOOLON_MODE] = 1.0; }
    else if (code == 103) ms[MS_TOOLON] = 0.0;
    else if (code == 200 && HAS(W_D) && isfinite(w->val[W_D])) {
        double d = w->val[W_D];
        ms[MS_EAREA] = (0.5 <= d && d <= 5.0) ? M_PI * d * d / 4.0 : 0.0;
        if (ms[MS_EAREA] > 0) m->stats[ST_VOLUMETRIC] = 1;
    } else if (code == 221 && HAS(W_S) && isfinite(w->val[W_S]) && 0.0 <= w->val[W_S] && w->val[W_S] <= 1000.0) {
        int t = (HAS(W_T) && 0 <= w->val[W_T] && w->val[W_T] < N_TOOLS) ? (int)w->val[W_T] : (int)ms[MS_TOOL];
        if (t < N_TOOLS) ms[MS_FLOW + t] = w->val[W_S] / 100.0;  /* tools 16..254 print at 100 % */
        m->stats[ST_FLOW_SET]++;
    }
}

static inline int line_action(Machine *m, const Words *w, int *mo_out)
{
    double *ms = m->ms;
    uint32_t has = w->has;
    int act = ACT_NONE, lmotion = -1, nonmotion = 0;
    for (int k = 0; k < w->ng; k++) {
        int mo;
        int a = apply_g(m, w->g[k], &mo, &nonmotion);
        if (a != ACT_NONE && (act == ACT_NONE || act == ACT_MOVE)) act = a;
        if (mo >= 0) lmotion = mo;
    }
    if (w->mcode >= 0) apply_m(m, w->mcode, w);
    if (HAS(W_T) && w->mcode != 221) {
        double t = w->val[W_T];
        if (0 <= t && t < 255) ms[MS_TOOL] = (double)(int)t;
    }
    if (HAS(W_F) && w->val[W_F] > 0) ms[MS_FEED] = w->val[W_F] * ms[MS_SCALE];
    *mo_out = -1;
    if (act == ACT_HOME || act == ACT_SETPOS) return act;
    int axes = HAS(W_X) || HAS(W_Y) || HAS(W_Z) || HAS(W_E) || HAS(W_A);
    int arc_words = HAS(W_I) || HAS(W_J) || HAS(W_R);
    if ((lmotion >= 0 || !nonmotion) && axes) { *mo_out = lmotion >= 0 ? lmotion : (int)ms[MS_MOTION]; return ACT_MOVE; }
    if ((lmotion == 2 || lmotion == 3) && arc_words) { *mo_out = lmotion; return ACT_MOVE; }
    return ACT_NONE;
}

static void home(double *ms, uint32_t has)
{
    int all = !(HAS(W_X) || HAS(W_Y) || HAS(W_Z));
    if (all || HAS(W_X)) { ms[MS_LX] = 0.0; ms[MS_OX] = 0.0; }
    if (all || HAS(W_Y)) { ms[MS_LY] = 0.0; ms[MS_OY] = 0.0; }
    if (all || HAS(W_Z)) { ms[MS_LZ] = 0.0; ms[MS_OZ] = 0.0; }
}

static void set_position(double *ms, const Words *w)
{
    uint32_t has = w->has;
    double sc = ms[MS_SCALE];
    static const int words[3] = {W_X, W_Y, W_Z}, los[3] = {MS_LX, MS_LY, MS_LZ}, oos[3] = {MS_OX, MS_OY, MS_OZ};
    if (!(HAS(W_X) || HAS(W_Y) || HAS(W_Z) || HAS(W_E))) {
        for (int k = 0; k < 3; k++) { ms[oos[k]] += ms[los[k]]; ms[los[k]] = 0.0; }
        ms[MS_E] = 0.0;
    }
    for (int k = 0; k < 3; k++) {
        if (HAS(words[k]) && isfinite(w->val[words[k]])) {
            ms[oos[k]] += ms[los[k]] - w->val[words[k]] * sc;
            ms[los[k]] = w->val[words[k]] * sc;
        }
    }
    if (HAS(W_E) && isfinite(w->val[W_E])) ms[MS_E] = w->val[W_E] * sc;
}

static inline double advance_axes(double *ms, const Words *w)
{
    uint32_t has = w->has;
    double sc = ms[MS_SCALE];
    int absolute = ms[MS_ABS] > 0;
    if (HAS(W_X) && isfinite(w->val[W_X])) ms[MS_LX] = absolute ? w->val[W_X] * sc : ms[MS_LX] + w->val[W_X] * sc;
    if (HAS(W_Y) && isfinite(w->val[W_Y])) ms[MS_LY] = absolute ? w->val[W_Y] * sc : ms[MS_LY] + w->val[W_Y] * sc;
    if (HAS(W_Z) && isfinite(w->val[W_Z])) ms[MS_LZ] = absolute ? w->val[W_Z] * sc : ms[MS_LZ] + w->val[W_Z] * sc;
    int we = HAS(W_E) ? W_E : W_A;
    if (!HAS(we) || !isfinite(w->val[we])) return 0.0;
    double de = (ms[MS_EREL] > 0 || !absolute) ? w->val[we] * sc : w->val[we] * sc - ms[MS_E];
    ms[MS_E] += de;
    return ms[MS_EAREA] > 0 ? de / ms[MS_EAREA] : de;
}

static inline void account_filament(double *ms, double *fs, double de, double flow, int xy_move)
{
    ms[MS_CMD] += de;
    ms[MS_FED] += de * flow;
    if (ms[MS_CMD] > ms[MS_CMD_HIGH]) ms[MS_CMD_HIGH] = ms[MS_CMD];
    if (ms[MS_FED] > ms[MS_FED_HIGH]) {
        if (!xy_move) fs[FS_EONLY_FED] += ms[MS_FED] - ms[MS_FED_HIGH];
        ms[MS_FED_HIGH] = ms[MS_FED];
    }
}

/* arcs.py: arc_geometry; returns ok */
static int arc_geometry(double x0, double y0, double x1, double y1, int ccw, int has_ij, int has_r, double i_off,
                        double j_off, double r, double chord_tol, double *o, long long *k_out)
{
    double dxy = hypot(x1 - x0, y1 - y0), cx, cy;
    *k_out = 1;
    if (has_ij) { cx = x0 + i_off; cy = y0 + j_off; }
    else if (has_r && dxy > 1e-12) {
        double h2 = r * r - dxy * dxy / 4.0;
        double h = h2 > 0 ? sqrt(h2) : 0.0;
        double sgn = (ccw == (r > 0)) ? 1.0 : -1.0;
        cx = (x0 + x1) / 2.0 - sgn * h * (y1 - y0) / dxy;
        cy = (y0 + y1) / 2.0 + sgn * h * (x1 - x0) / dxy;
    } else return 0;
    double r0 = hypot(x0 - cx, y0 - cy), r1 = hypot(x1 - cx, y1 - cy);
    double a0 = atan2(y0 - cy, x0 - cx);
    double sweep = atan2(y1 - cy, x1 - cx) - a0;
    if (ccw) { if (sweep <= 1e-12) sweep += 2.0 * M_PI; }
    else if (sweep >= -1e-12) sweep -= 2.0 * M_PI;
    if (!(isfinite(r0) && isfinite(r1) && isfinite(sweep))) return 0;
    long long k = 1;
    if (r0 > 1e-9 && chord_tol < r0) {
        double step = 2.0 * acos(1.0 - chord_tol / r0);
        if (step > 1e-12) { double q = fabs(sweep) / step; k = (long long)ceil(q < 1e6 ? q : 1e6); }
        else k = 1000000;
    }
    k = k < 1000000 ? k : 1000000;
    *k_out = k > 1 ? k : 1;
    o[0] = cx; o[1] = cy; o[2] = r0; o[3] = r1; o[4] = a0; o[5] = sweep;
    return 1;
}

static long long arc_chords(double *ms, long long k, double sweep, double r0, double r1, int *capped)
{
    double length = fabs(sweep) * (r0 > r1 ? r0 : r1);
    long long cap = 1 + (long long)((length < 1e9 ? length : 1e9) / ARC_MIN_CHORD_MM);
    cap = cap < ARC_MAX_CHORDS ? cap : ARC_MAX_CHORDS;
    if (ms[MS_ARC_CHORDS] > ms[MS_ARC_BUDGET]) cap = cap < 16 ? cap : 16;
    long long k2 = k < cap ? k : cap;
    k2 = k2 > 1 ? k2 : 1;
    ms[MS_ARC_CHORDS] += (double)k2;
    *capped = k2 < k;
    return k2;
}

static int emit_arc(Machine *m, const double *p, const double *arc, long long k, double de, int64_t line, int64_t tool)
{
    double x0 = p[0], y0 = p[1], z0 = p[2], x1 = p[3], y1 = p[4], z1 = p[5];
    double cx = arc[0], cy = arc[1], r0 = arc[2], r1 = arc[3], a0 = arc[4], sweep = arc[5];
    double px = x0, py = y0;
    for (long long q = 1; q <= k; q++) {
        double t = (double)q / (double)k, qx, qy;
        double rr = r0 + (r1 - r0) * t;
        if (q == k) { qx = x1; qy = y1; }
        else { qx = cx + rr * cos(a0 + sweep * t); qy = cy + rr * sin(a0 + sweep * t); }
        if (push_seg(m, px, py, qx, qy, z0 + (z1 - z0) * t, de / (double)k, line, tool) < 0) return -1;
        px = qx; py = qy;
    }
    return 0;
}

/* hypot(dx, dy) > len, exactly as numba's math.hypot decides it, without the libm call unless
 * the squared length is within 1e-6 of len^2 (where rounding could matter) */
static inline int longer_than(double dx, double dy, double len)
{
    double q = dx * dx + dy * dy, l2 = len * len;
    if (q > l2 * 1.000001) return 1;
    if (q < l2 * 0.999999) return 0;
    return hypot(dx, dy) > len;  /* also NaN: neither comparison above holds */
}

/* _move: returns 1 when a travel (non-extruding XY move) happened, 0 otherwise, -1 on memory error */
static int move(Machine *m, const Words *w, int mo, int64_t line)
{
    double *ms = m->ms, *fs = m->fs;
    uint32_t has = w->has;
    double x0 = ms[MS_LX] + ms[MS_OX], y0 = ms[MS_LY] + ms[MS_OY], z0 = ms[MS_LZ] + ms[MS_OZ];
    double de = advance_axes(ms, w);
    double x1 = ms[MS_LX] + ms[MS_OX], y1 = ms[MS_LY] + ms[MS_OY], z1 = ms[MS_LZ] + ms[MS_OZ];
    int64_t tool = (int64_t)ms[MS_TOOL];
    double flow = tool < N_TOOLS ? ms[MS_FLOW + tool] : 1.0;
    int absurd = !(fabs(x1) <= ABSURD_MM && fabs(y1) <= ABSURD_MM && fabs(z1) <= ABSURD_MM && fabs(de) <= ABSURD_MM
                   && fabs(x0) <= ABSURD_MM && fabs(y0) <= ABSURD_MM && fabs(z0) <= ABSURD_MM);
    if (absurd) { flag(m->stats, ST_ABSURD, ST_FIRST_ABSURD, line); return 0; }
    int arc = mo == 2 || mo == 3;
    /* finite and within ABSURD_MM here: dx, dy cannot overflow; dxy > 0 iff either is non-zero */
    double dx = x1 - x0, dy = y1 - y0;
    int moved = longer_than(dx, dy, 1e-12);
    account_filament(ms, fs, de, flow, moved || arc);
    int extruding = de > 1e-9 || (ms[MS_TOOLON_MODE] > 0 && ms[MS_TOOLON] > 0 && !HAS(W_E));
    double fed = de > 1e-9 ? de * flow : 0.0;
    if (arc) {
        m->stats[ST_ARCS]++;
        double sc = ms[MS_SCALE], g[6];
        long long k;
        int ok = arc_geometry(x0, y0, x1, y1, mo == 3, HAS(W_I) || HAS(W_J), HAS(W_R),
                              HAS(W_I) ? w->val[W_I] * sc : 0.0, HAS(W_J) ? w->val[W_J] * sc : 0.0,
                              HAS(W_R) ? w->val[W_R] * sc : 0.0, m->chord_tol, g, &k);
        if (ok && !(g[2] <= ABSURD_MM && g[3] <= ABSURD_MM)) ok = 0;
        if (!ok) flag(m->stats, ST_ARC_BAD, ST_FIRST_ARC_BAD, line);
        else {
            if (!extruding) return dx != 0.0 || dy != 0.0 || fabs(g[5]) > 0;
            int capped;
            k = arc_chords(ms, k, g[5], g[2], g[3], &capped);
            if (capped) flag(m->stats, ST_ARC_CAPPED, ST_FIRST_ARC_CAPPED, line);
            fs[FS_XY_CMD] += de;
            fs[FS_XY_FED] += fed;
            double p[6] = {x0, y0, z0, x1, y1, z1};
            return emit_arc(m, p, g, k, fed, line, tool);
        }
    }
    if (!moved) return 0;
    if (!extruding) return 1;
    fs[FS_XY_CMD] += de > 0.0 ? de : 0.0;
    fs[FS_XY_FED] += fed;
    return push_seg(m, x0, y0, x1, y1, z1, fed, line, tool);
}

static void record_probe(double *row, const double *ms)
{
    static const int slots[11] = {MS_LX, MS_LY, MS_LZ, MS_OX, MS_OY, MS_OZ, MS_E, MS_FEED, MS_ABS, MS_EREL, MS_TOOL};
    for (int c = 0; c < 11; c++) row[c] = ms[slots[c]];
    row[11] = ms[MS_SCALE] != 1.0 ? 1.0 : 0.0;
    row[12] = (ms[MS_TOOLON_MODE] > 0 && ms[MS_TOOLON] > 0) ? 1.0 : 0.0;
}

static void new_state(double *ms, int e_rel_init, double e_area_init, Py_ssize_t n_bytes)
{
    memset(ms, 0, sizeof(double) * N_MS);
    ms[MS_ARC_BUDGET] = (double)(ARC_BUDGET_BASE + ARC_BUDGET_PER_BYTE * (int64_t)n_bytes);
    ms[MS_ABS] = 1.0;
    ms[MS_EREL] = e_rel_init ? 1.0 : 0.0;
    ms[MS_SCALE] = 1.0;
    ms[MS_MOTION] = 1.0;
    ms[MS_EAREA] = e_area_init;
    for (int t = 0; t < N_TOOLS; t++) ms[MS_FLOW + t] = 1.0;
}

/* the main loop of kernel.run_kernel; returns 0, or -1 with a Python error set */
static int run_lines(Machine *m, const unsigned char *buf, Py_ssize_t n, const int64_t *probes, Py_ssize_t np_,
                     double *probe_state)
{
    Words w;
    memset(&w, 0, sizeof w);
    Py_ssize_t i = 0, npb = 0;
    int64_t line = 1;
    while (i <= n) {
        while (npb < np_ && probes[npb] <= line) {
            if (probes[npb] == line) record_probe(probe_state + N_PROBE * npb, m->ms);
            npb++;
        }
        if (i == n) break;
        i = lex_line(buf, i, n, &w);
        if (w.cmt_at >= 0) {
            if (out_reserve(&m->cmt, 1) < 0) return -1;
            int64_t *c = OUT_PTR(&m->cmt, int64_t) + 2 * m->cmt.n++;
            c[0] = w.cmt_at; c[1] = line;
        }
        if (w.extended) m->stats[ST_UNKNOWN]++;
        if (w.bad & BAD_BYTES) flag(m->stats, ST_BAD, ST_FIRST_BAD, line);
        if (w.bad & BAD_WORD) flag(m->stats, ST_MALFORMED, ST_FIRST_MALFORMED, line);
        int mo, act = line_action(m, &w, &mo);
        if (act == ACT_HOME) home(m->ms, w.has);
        else if (act == ACT_SETPOS) set_position(m->ms, &w);
        else if (act == ACT_MOVE) {
            int travelled = move(m, &w, mo, line);
            if (travelled < 0) return -1;
            if (travelled) {
                if (out_reserve(&m->travel, 1) < 0) return -1;
                OUT_PTR(&m->travel, int64_t)[m->travel.n++] = line;
            }
        }
        if (i < n) i++;
        else m->stats[ST_NONL] = 1;
        line++;
    }
    if (m->ms[MS_TOOLON_MODE] > 0) m->stats[ST_TOOLON] = 1;
    m->stats[ST_LINES] = line - 1;
    m->stats[ST_SEG] = m->seg[SEG_A].n;
    m->stats[ST_TRAVEL] = m->travel.n;
    m->stats[ST_CMT] = m->cmt.n;
    m->fs[FS_CMD_HIGH] = m->ms[MS_CMD_HIGH];
    m->fs[FS_FED_HIGH] = m->ms[MS_FED_HIGH];
    return 0;
}

static PyObject *finish(Out *o)
{
    if (PyByteArray_Resize(o->ba, o->n * o->width) < 0) return NULL;
    PyObject *r = o->ba;
    o->ba = NULL;
    return r;
}

static PyObject *ckernel_run(PyObject *self, PyObject *args)
{
    Py_buffer data, probes;
    double chord_tol, e_area_init;
    int e_rel_init;
    if (!PyArg_ParseTuple(args, "y*y*dpd", &data, &probes, &chord_tol, &e_rel_init, &e_area_init)) return NULL;
    Py_ssize_t n = data.len, np_ = probes.len / 8;
    Machine m;
    memset(&m, 0, sizeof m);
    m.chord_tol = chord_tol;
    new_state(m.ms, e_rel_init, e_area_init, n);
    PyObject *probe_ba = PyByteArray_FromStringAndSize(NULL, np_ * N_PROBE * 8), *result = NULL;
    Py_ssize_t cap = n / 32 + 16;
    int ok = probe_ba != NULL && out_init(&m.travel, cap / 4 + 16, 8) == 0 && out_init(&m.cmt, 64, 16) == 0;
    for (int c = 0; ok && c < N_SEG; c++) ok = out_init(&m.seg[c], cap, SEG_WIDTH[c]) == 0;
    if (ok) {
        double *ps = (double *)PyByteArray_AS_STRING(probe_ba);
        for (Py_ssize_t k = 0; k < np_ * N_PROBE; k++) ps[k] = NAN;
        /* the GIL stays held: the output bytearrays are resized as the segments come */
        if (run_lines(&m, (const unsigned char *)data.buf, n, (const int64_t *)probes.buf, np_, ps) == 0) {
            PyObject *items[11] = {NULL};
            for (int c = 0; c < N_SEG; c++) items[c] = finish(&m.seg[c]);
            items[6] = finish(&m.travel);
            items[7] = finish(&m.cmt);
            Py_INCREF(probe_ba);
            items[8] = probe_ba;
            items[9] = PyByteArray_FromStringAndSize((const char *)m.stats, sizeof m.stats);
            items[10] = PyByteArray_FromStringAndSize((const char *)m.fs, sizeof m.fs);
            result = PyTuple_New(11);
            for (int c = 0; c < 11; c++) {
                if (!items[c] && result) { Py_CLEAR(result); }
                if (result) PyTuple_SET_ITEM(result, c, items[c]);
                else Py_XDECREF(items[c]);
            }
        }
    }
    for (int c = 0; c < N_SEG; c++) Py_XDECREF(m.seg[c].ba);
    Py_XDECREF(m.travel.ba); Py_XDECREF(m.cmt.ba);
    Py_XDECREF(probe_ba);
    PyBuffer_Release(&data);
    PyBuffer_Release(&probes);
    return result;
}

static PyMethodDef methods[] = {
    {"run", ckernel_run, METH_VARARGS,
     "run(buf, probes, chord_tol, e_rel_init, e_area_init) -> (start, end, z, e, line, tool, travel_line, cmt, "
     "probe_state, stats, fstats) as bytearrays (layouts: layerwatch.gcode.kernel_abi)"},
    {NULL, NULL, 0, NULL}};

static struct PyModuleDef module = {PyModuleDef_HEAD_INIT, "_ckernel",
                                    "Ahead-of-time compiled G-code kernel (see kernel.py).", -1, methods};

PyMODINIT_FUNC PyInit__ckernel(void)
{
    for (int k = 0; k < 309; k++) POW10[k] = pow(10.0, (double)k);
    static const char tag_first[] = "LlZzTtFfCcBb'Ee";
    for (const char *p = tag_first; *p; p++) TAG_FIRST[(unsigned char)*p] = 1;
    PyObject *mod = PyModule_Create(&module);
    if (!mod) return NULL;
    PyObject *abi = Py_BuildValue("{s:i,s:i,s:i,s:i,s:i,s:i,s:d,s:i,s:i,s:i,s:d}", "N_STATS", N_STATS,
                                  "N_FSTATS", N_FSTATS, "N_PROBE", N_PROBE, "N_MS", N_MS, "MS_FLOW", MS_FLOW,
                                  "N_TOOLS", N_TOOLS, "ABSURD_MM", ABSURD_MM, "ARC_MAX_CHORDS", ARC_MAX_CHORDS,
                                  "ARC_BUDGET_BASE", ARC_BUDGET_BASE, "ARC_BUDGET_PER_BYTE", ARC_BUDGET_PER_BYTE,
                                  "ARC_MIN_CHORD_MM", ARC_MIN_CHORD_MM);
    if (!abi || PyModule_AddObject(mod, "ABI", abi) < 0 || PyModule_AddStringConstant(mod, "SOURCE_KEY", LW_SOURCE_KEY) < 0) {
        Py_XDECREF(abi);
        Py_DECREF(mod);
        return NULL;
    }
    return mod;
}
