/*
 * course.c -- a small CPSC 102 course ray tracer, written straight from the course notes
 * (shared/notes/course-format.md and the finite-plane chapter, shared/seed/000_*.txt), as
 * independent test material for rtval.  Plain C99, double precision throughout.
 *
 *   course COLUMNS [ROWS] [--hits FILE] < scene > out.ppm
 *
 * Reads a scene in either dialect from stdin, writes the shaded course image as a binary P6
 * PPM (top row first) to stdout.  ROWS defaults to (int)(world_h / world_w * COLUMNS).
 * --hits FILE also writes the primary-ray hit dump, one line per pixel in image order:
 *   "column row object t"   column 0..W-1, row = image row (0 = top), object = index among
 *   the non-light objects in file order or -1 on a miss, t with "%.17g" (0 on a miss).
 *
 * Exit status: 0 success; 2 malformed scene (one line "stdin:LINE:COL: message" on stderr);
 * 64 command-line usage error; 1 an output could not be written.
 *
 * Compile-time parameters (values):
 *   -DMAX_DIST=D      reflection stops once total_dist >= D (default 50000; 20..50000 seen)
 *   -DTMIN=T          plane/fplane/tplane hit needs t > T (default 0: the notes)
 *   -DTILE_OFF=K      tile-parity offset (default 10000, the notes; 1000 in one program)
 *   -DMAX_BOUNCES=N   safety cap on reflection depth (default 1000000; a warning when hit)
 *
 * Compile-time switches reproducing real student deviations and bugs (default: off = the
 * notes).  Each is one -D flag:
 *   -DEDGES_OPEN      finite-plane bounds open: 0 < u < w, 0 < v < h (notes: closed <=)
 *   -DCLIP_GE         screen clip z >= 0 instead of z > 0 (a plane lying in z = 0 vanishes)
 *   -DTIES_LAST       exact tie in t: the LATER object in the file wins (head-inserted list)
 *   -DTMIN=1e-4       plane t threshold t > 1e-4 (1e-5 also seen) instead of t > 0
 *   -DCLIP_SPHERES    the screen clip (z > 0 is a miss) applies to spheres too
 *   -DREFLECT_SEGMENT each shaded hit divides by the length of its last segment t instead of
 *                     the total path length total_dist (MAX_DIST still tests total_dist)
 *   -DROWS_SHIFTED    image row r samples (H - r)/(H - 1) instead of (H - 1 - r)/(H - 1):
 *                     every row is one row higher, the top row lies above the window
 *   -DTILE_OFF=1000   tile parity offset 1000 (only differs beyond 1000 tiles from point)
 *   -DTILE_NOPROJECT  tiled plane: xdir is only made unit, not projected onto the plane
 *                     (a tilted xdir then gives a non-orthonormal frame)
 *   -DALIAS_XFORM     vl_xform3(newhit, rotmat, newhit) in place (the seed's own line):
 *                     newhit.x is overwritten before newhit.y (and z) are computed, so tilted
 *                     finite planes come out mirrored/sheared.  Only the finite-plane hit
 *                     test (where the notes show it); tiled-plane coordinates stay correct
 *   -DINV_SQUARE      diffuse falls off as 1/d^2 instead of 1/d (a bug)
 *   -DNO_SHADOWS      no shadow rays at all (a bug)
 *   -DSPOT_FULL_ANGLE a spotlight's theta taken as the cone's full angle, not the half-angle
 *                     (a bug: the lit cone is half as wide)
 *   -DQUANT_ROUND     the pixel is floor(255 I + 0.5), rounded instead of floored (a bug)
 *   -DROWS_FLIPPED    the bottom row written first: the image upside down (a bug)
 *   -DDIR_NOT_UNIT    the primary ray's direction is not made unit, so t (and the path
 *                     length the shading divides by) is not a distance (a bug)
 *   -DSELF_SHADOW     shadow rays do not skip the object they start on: speckles of
 *                     shadow where rounding puts that object at a tiny t > 0 (a bug)
 *   -DTILE_SWAP       a tiled plane's foreground and background swapped (a bug)
 *   -DAMB_AFTER       the ambient added after dividing by the path length (a bug: it is
 *                     not divided, so it saturates)
 *   -DOFF_BY_ONE      the pixel mapping divides by W and H instead of W - 1 and H - 1 (a bug)
 *   -DEMIS_SWAP       a light's red and blue emissivity read in the other order (a bug)
 *   -DCLAMP_AFTER     the pixel is (unsigned char)(int)(255 I): no clamp, so intensities
 *                     above 1 wrap around (a bug)
 *   -DHDR_256         the PPM header says maxval 256 over one-byte samples (a bug: a
 *                     maxval above 255 means two bytes a sample)
 * One more variant from the notes, beyond the list above:
 *   -DTILE_ADD_FIRST  tile parity floor((OFF + u)/w) instead of floor(OFF + u/w): OFF is
 *                     added before dividing, which shifts the pattern unless w divides OFF
 */
#include <ctype.h>
#include <math.h>
#include <stdarg.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>

#ifndef MAX_DIST
#define MAX_DIST 50000.0
#endif
#ifndef TMIN
#define TMIN 0.0
#endif
#ifndef TILE_OFF
#define TILE_OFF 10000.0
#endif
#ifndef MAX_BOUNCES
#define MAX_BOUNCES 1000000L
#endif

#ifdef CLIP_GE
#define CLIPPED(z) ((z) >= 0.0)
#else
#define CLIPPED(z) ((z) > 0.0)
#endif

/* ------------------------------------------------------------------ vector helpers (vl_*) */

static double dot3(const double a[3], const double b[3])
{
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
}

static void diff3(double out[3], const double a[3], const double b[3])
{
    out[0] = a[0] - b[0];
    out[1] = a[1] - b[1];
    out[2] = a[2] - b[2];
}

static void scale3(double out[3], double s, const double a[3])
{
    out[0] = s * a[0];
    out[1] = s * a[1];
    out[2] = s * a[2];
}

static void sum3(double out[3], const double a[3], const double b[3])
{
    out[0] = a[0] + b[0];
    out[1] = a[1] + b[1];
    out[2] = a[2] + b[2];
}

static double length3(const double a[3])
{
    return sqrt(dot3(a, a));
}

static void unit3(double out[3], const double a[3])
{
    double n = length3(a);
    out[0] = a[0] / n;
    out[1] = a[1] / n;
    out[2] = a[2] / n;
}

static void cross3(double out[3], const double a[3], const double b[3])
{
    double t[3];
    t[0] = a[1] * b[2] - a[2] * b[1];
    t[1] = a[2] * b[0] - a[0] * b[2];
    t[2] = a[0] * b[1] - a[1] * b[0];
    memcpy(out, t, sizeof t);
}

/* The course's vl_xform3(out, m, in): out = m . in, element by element INTO out.  Called with
 * out == in (ALIAS_XFORM) it reads the already overwritten out[0] when computing out[1]. */
static void xform3(double *out, const double m[3][3], const double *in)
{
    out[0] = dot3(m[0], in);
    out[1] = dot3(m[1], in);
    out[2] = dot3(m[2], in);
}

/* ------------------------------------------------------------------ scene model */

enum { K_SPHERE, K_PLANE, K_FPLANE, K_TPLANE };

typedef struct {
    double amb[3], dif[3], spec[3];
} mat_t;

typedef struct {
    int kind;
    mat_t mat;          /* tplane: foreground */
    mat_t bg;           /* tplane: background */
    double center[3], radius;           /* sphere */
    double normal[3];                   /* unit normal (rotmat row 2) */
    double point[3];                    /* a point / the lower-left corner */
    double orient[3];                   /* as given */
    double size[2];                     /* fplane size, tplane tile size */
    double rotmat[3][3];                /* rows x^, y^, n^ */
} obj_t;

typedef struct {
    double emis[3], center[3];
    int spot;                           /* spotlight (code 11): lights H only inside its cone */
    double axis[3], cos_theta;          /* unit(aim - center), cos(half-angle) */
} light_t;

static double g_window[2], g_view[3];
static obj_t *g_obj;
static int g_nobj, g_capobj;
static light_t *g_light;
static int g_nlight, g_caplight;

/* ------------------------------------------------------------------ input and errors */

typedef struct {
    const char *s;
    int len, line, col;
} tok_t;

static char *g_text;
static tok_t *g_tok;
static int g_ntok, g_captok;
static int *g_line_first, *g_line_count, g_nlines; /* tokens per line, by line number - 1 */
static int g_eof_line = 1, g_eof_col = 1;

static void fail_at(int line, int col, const char *fmt, ...)
{
    va_list ap;
    fprintf(stderr, "stdin:%d:%d: ", line, col);
    va_start(ap, fmt);
    vfprintf(stderr, fmt, ap);
    va_end(ap);
    fputc('\n', stderr);
    exit(2);
}

static void *xrealloc(void *p, size_t n)
{
    void *q = realloc(p, n ? n : 1);
    if (!q) {
        fprintf(stderr, "course: out of memory\n");
        exit(2);
    }
    return q;
}

static void read_input(void)
{
    size_t cap = 1 << 16, n = 0, k;
    char *buf = xrealloc(NULL, cap);
    while ((k = fread(buf + n, 1, cap - n - 1, stdin)) > 0) {
        n += k;
        if (n + 1 >= cap) {
            cap *= 2;
            buf = xrealloc(buf, cap);
        }
    }
    buf[n] = '\0';
    g_text = buf;

    /* split into lines (\n, \r\n or lone \r), drop '#' comments, split on space/tab/\f/\v */
    {
        size_t i = 0;
        int line = 1, nl_cap = 0;
        if (n >= 3 && (unsigned char)buf[0] == 0xEF && (unsigned char)buf[1] == 0xBB &&
            (unsigned char)buf[2] == 0xBF)
            i = 3;                                      /* UTF-8 byte order mark */
        while (1) {
            size_t start = i, end, j;
            int col;
            while (i < n && buf[i] != '\n' && buf[i] != '\r')
                i++;
            end = i;
            if (line > nl_cap) {
                nl_cap = nl_cap ? 2 * nl_cap : 256;
                g_line_first = xrealloc(g_line_first, nl_cap * sizeof(int));
                g_line_count = xrealloc(g_line_count, nl_cap * sizeof(int));
            }
            g_line_first[line - 1] = g_ntok;
            for (j = start; j < end; j++)
                if (buf[j] == '#') {
                    end = j;
                    break;
                }
            j = start;
            col = 1;
            while (j < end) {
                if (buf[j] == ' ' || buf[j] == '\t' || buf[j] == '\f' || buf[j] == '\v') {
                    j++;
                    col++;
                    continue;
                }
                if (g_ntok == g_captok) {
                    g_captok = g_captok ? 2 * g_captok : 1024;
                    g_tok = xrealloc(g_tok, g_captok * sizeof(tok_t));
                }
                g_tok[g_ntok].s = buf + j;
                g_tok[g_ntok].line = line;
                g_tok[g_ntok].col = col;
                {
                    size_t s0 = j;
                    while (j < end && buf[j] != ' ' && buf[j] != '\t' && buf[j] != '\f' &&
                           buf[j] != '\v')
                        j++;
                    g_tok[g_ntok].len = (int)(j - s0);
                    col += (int)(j - s0);
                }
                g_eof_line = line;
                g_eof_col = col;
                g_ntok++;
            }
            g_line_count[line - 1] = g_ntok - g_line_first[line - 1];
            g_nlines = line;
            if (i >= n)
                break;
            if (buf[i] == '\r' && i + 1 < n && buf[i + 1] == '\n')
                i++;
            i++;
            line++;
        }
    }
}

/* a C-style decimal literal: [+-]? (digits [. digits*] | . digits) ([eE] [+-]? digits)? */
static int num_syntax(const tok_t *t)
{
    const char *s = t->s;
    int n = t->len, i = 0, digits = 0, ed = 0;
    if (i < n && (s[i] == '+' || s[i] == '-'))
        i++;
    while (i < n && isdigit((unsigned char)s[i])) {
        i++;
        digits++;
    }
    if (i < n && s[i] == '.') {
        i++;
        while (i < n && isdigit((unsigned char)s[i])) {
            i++;
            digits++;
        }
    }
    if (!digits)
        return 0;
    if (i < n && (s[i] == 'e' || s[i] == 'E')) {
        i++;
        if (i < n && (s[i] == '+' || s[i] == '-'))
            i++;
        while (i < n && isdigit((unsigned char)s[i])) {
            i++;
            ed++;
        }
        if (!ed)
            return 0;
    }
    return i == n;
}

static int tok_ieq(const tok_t *t, const char *w)
{
    int i, n = (int)strlen(w);
    if (t->len != n)
        return 0;
    for (i = 0; i < n; i++)
        if (tolower((unsigned char)t->s[i]) != w[i])
            return 0;
    return 1;
}

static int nonfinite_word(const tok_t *t)
{
    tok_t u = *t;
    if (u.len > 0 && (u.s[0] == '+' || u.s[0] == '-')) {
        u.s++;
        u.len--;
    }
    return tok_ieq(&u, "nan") || tok_ieq(&u, "inf") || tok_ieq(&u, "infinity");
}

static int looks_number(const tok_t *t)
{
    return num_syntax(t) || nonfinite_word(t);
}

/* short printable copy of a token for messages */
static const char *show(const tok_t *t)
{
    static char b[64];
    int i, k = 0;
    for (i = 0; i < t->len && k < 44; i++) {
        unsigned char c = (unsigned char)t->s[i];
        b[k++] = (c >= 32 && c < 127) ? (char)c : '?';
    }
    if (i < t->len) {
        b[k++] = '.';
        b[k++] = '.';
        b[k++] = '.';
    }
    b[k] = '\0';
    return b;
}

static double tok_value(const tok_t *t, const char *what)
{
    char b[512];
    double v;
    if (nonfinite_word(t))
        fail_at(t->line, t->col, "%s: '%s' is not a finite number", what, show(t));
    if (t->len >= (int)sizeof b)
        fail_at(t->line, t->col, "%s: number '%s' is too long", what, show(t));
    memcpy(b, t->s, t->len);
    b[t->len] = '\0';
    v = strtod(b, NULL);
    if (!isfinite(v))
        fail_at(t->line, t->col, "%s: number '%s' is out of range (not finite)", what, show(t));
    return v;
}

/* forms: 0 pointlight 1 sphere 2 plane 3 fplane 4 tplane 5 spotlight 6 fplanetex
 * 7 sphere_pixmap (keywords); 8 procedural sphere (19) 9 procedural plane (20) 10 textured
 * plane (17) 11 textured sphere (26): the geometry of their kind, the extra fields read and
 * not used (procedural shaders and textures are not implemented: the MAT shades them) */
static const char *KEYWORDS[] = {"pointlight", "sphere", "plane", "fplane", "tplane",
                                 "spotlight", "fplanetex", "sphere_pixmap"};
static const int CODES[] = {10, 13, 14, 15, 16, 11, -1, -1, 19, 20, 17, 26};
#define NFORMS 12
static const int FORM_KIND[] = {0, 1, 2, 3, 4, 5, 3, 1, 1, 2, 3, 1};
/* kinds the course used that this tracer does not implement */
static const char *UNSUP_WORDS[] = {"ellipsoid", "projector", "paraboloid", "cylinder", "cone",
                                    "hyperboloid", "torus", "triangle", "disk", "lens"};
static int g_nflags;            /* cd's header flags 9000/9001: a number after every MAT each */

static int keyword_index(const tok_t *t)
{
    int i;
    for (i = 0; i < 8; i++)
        if (tok_ieq(t, KEYWORDS[i]))
            return i;
    return -1;
}

static int unsupported_word(const tok_t *t)
{
    size_t i;
    for (i = 0; i < sizeof UNSUP_WORDS / sizeof UNSUP_WORDS[0]; i++)
        if (tok_ieq(t, UNSUP_WORDS[i]))
            return 1;
    return 0;
}

/* Dialect from the first line-start token after the five header numbers: a word means the
 * keyword dialect, a number the numeric dialect (free text on header lines: numeric). */
static int detect_numeric(void)
{
    int count = 0, free_text = 0, l;
    for (l = 0; l < g_nlines; l++) {
        int n = g_line_count[l], lead = 0;
        const tok_t *tk = g_tok + g_line_first[l];
        if (!n)
            continue;
        if (count >= 5)
            return looks_number(&tk[0]);
        while (lead < n && looks_number(&tk[lead]))
            lead++;
        if (lead == 0)
            return free_text;
        count += lead;
        if (count > 5)
            return 1;
        if (lead < n) {
            if (count == 5 && (keyword_index(&tk[lead]) >= 0 || unsupported_word(&tk[lead])))
                return 0;
            free_text = 1;
        }
    }
    return free_text;
}

/* --- reading groups: keyword dialect (token stream) */

static int g_pos;               /* keyword: next token; numeric: next non-empty line index */
static int *g_content, g_ncontent; /* numeric: indices of non-empty lines */
static int g_numeric;

static void group(const char *what, const char *name, int n, const char *desc, double *out)
{
    int i;
    if (!g_numeric) {
        for (i = 0; i < n; i++) {
            const tok_t *t;
            if (g_pos >= g_ntok)
                fail_at(g_eof_line, g_eof_col, "%s: expected %d number%s for %s (%s), found "
                        "end of file", what, n, n == 1 ? "" : "s", name, desc);
            t = &g_tok[g_pos];
            if (!looks_number(t))
                fail_at(t->line, t->col, "%s: expected %d number%s for %s (%s), found '%s'",
                        what, n, n == 1 ? "" : "s", name, desc, show(t));
            out[i] = tok_value(t, what);
            g_pos++;
        }
    } else {
        int l, cnt, lead = 0;
        const tok_t *tk;
        if (g_pos >= g_ncontent)
            fail_at(g_eof_line, g_eof_col, "%s: expected %d number%s for %s (%s), found end "
                    "of file", what, n, n == 1 ? "" : "s", name, desc);
        l = g_content[g_pos++];
        cnt = g_line_count[l];
        tk = g_tok + g_line_first[l];
        while (lead < cnt && num_syntax(&tk[lead]))
            lead++;
        if (lead < n) {
            if (lead < cnt) {
                if (nonfinite_word(&tk[lead]))
                    tok_value(&tk[lead], what);
                fail_at(tk[lead].line, tk[lead].col, "%s: expected %d number%s for %s (%s), "
                        "found '%s'", what, n, n == 1 ? "" : "s", name, desc, show(&tk[lead]));
            }
            fail_at(tk[cnt - 1].line, tk[cnt - 1].col + tk[cnt - 1].len, "%s: expected %d "
                    "number%s for %s (%s) on one line, found end of line after %d", what, n,
                    n == 1 ? "" : "s", name, desc, lead);
        }
        for (i = 0; i < n; i++)
            out[i] = tok_value(&tk[i], what);
        /* anything after the numbers a group needs (text or further numbers) is ignored */
    }
}

static void read_mat(const char *what, mat_t *m, int background)
{
    int f;
    double skip;
    group(what, background ? "background ambient" : "ambient", 3, "r g b", m->amb);
    group(what, background ? "background diffuse" : "diffuse", 3, "r g b", m->dif);
    group(what, background ? "background specular" : "specular", 3, "r g b", m->spec);
    for (f = 0; f < g_nflags; f++)
        group(what, "header flag field", 1, "a number", &skip);
}

/* a file name (a texture): the next token, or the next line's first token */
static void skip_word(const char *what)
{
    if (g_numeric ? g_pos >= g_ncontent : g_pos >= g_ntok)
        fail_at(g_eof_line, g_eof_col, "%s: expected a file name, found end of file", what);
    g_pos++;
}

/* the fields a form adds after its kind's (read, not used) */
static void read_extras(int form, const char *what)
{
    double v[3];
    switch (form) {
    case 6: group(what, "brightness", 1, "", v); group(what, "texture size", 2, "", v);
            skip_word(what); break;
    case 7: group(what, "brightness", 1, "", v); group(what, "forward", 3, "", v);
            skip_word(what); break;
    case 8: case 9: group(what, "shader", 1, "", v); break;
    case 10: skip_word(what); group(what, "tile mode", 1, "", v); break;
    case 11: skip_word(what); break;
    }
}

/* the seed's frame: x^ = unit(orient - (orient.n^) n^), y^ = unit(n^ x x^), rows x^ y^ n^ */
static void make_frame(obj_t *o, const tok_t *at, const char *what, int project)
{
    double p[3], s[3], ln;
    scale3(s, dot3(o->orient, o->normal), o->normal);
    if (project)
        diff3(p, o->orient, s);
    else
        memcpy(p, o->orient, sizeof p);
    ln = length3(p);
    if (!(ln > 1e-12 * length3(o->orient)) || !isfinite(ln))
        fail_at(at->line, at->col, "%s: %s (%g, %g, %g) is parallel to the normal (or zero); "
                "give an in-plane direction", what, o->kind == K_TPLANE ? "xdir" : "orient",
                o->orient[0], o->orient[1], o->orient[2]);
    unit3(o->rotmat[0], p);
    memcpy(o->rotmat[2], o->normal, sizeof o->normal);
    cross3(s, o->rotmat[2], o->rotmat[0]);
    unit3(o->rotmat[1], s);
}

static void unit_normal(obj_t *o, const double raw[3], const tok_t *at, const char *what)
{
    double ln = length3(raw);
    if (!(ln > 0.0) || !isfinite(ln))
        fail_at(at->line, at->col, "%s: normal (%g, %g, %g) has no direction", what, raw[0],
                raw[1], raw[2]);
    unit3(o->normal, raw);
}

static const tok_t *cur_tok(void)
{
    if (!g_numeric)
        return g_pos < g_ntok ? &g_tok[g_pos] : &g_tok[g_ntok - 1];
    if (g_pos < g_ncontent)
        return &g_tok[g_line_first[g_content[g_pos]]];
    return &g_tok[g_ntok - 1];
}

static void read_object(int form)
{
    const char *what = form < 8 ? KEYWORDS[form] : "object";
    int kw = FORM_KIND[form];
    if (kw == 0 || kw == 5) {
        light_t L;
        memset(&L, 0, sizeof L);
        group(what, "emissivity", 3, "r g b", L.emis);
#ifdef EMIS_SWAP
        { double tt = L.emis[0]; L.emis[0] = L.emis[2]; L.emis[2] = tt; }   /* the bug */
#endif
        group(what, "center", 3, "x y z", L.center);
        if (kw == 5) {
            double aim[3], D[3], theta;
            group(what, "aim", 3, "x y z", aim);
            group(what, "theta", 1, "degrees", &theta);
            diff3(D, aim, L.center);
            unit3(L.axis, D);
#ifdef SPOT_FULL_ANGLE
            theta /= 2.0;                   /* the bug: theta taken as the cone's full angle */
#endif
            L.cos_theta = cos(theta * 3.14159265358979323846 / 180.0);
            L.spot = 1;
        }
        if (g_nlight == g_caplight) {
            g_caplight = g_caplight ? 2 * g_caplight : 8;
            g_light = xrealloc(g_light, g_caplight * sizeof(light_t));
        }
        g_light[g_nlight++] = L;
        return;
    }
    {
        obj_t o;
        double raw[3];
        const tok_t *at;
        memset(&o, 0, sizeof o);
        read_mat(what, &o.mat, 0);
        o.bg = o.mat;
        if (kw == 1) {
            o.kind = K_SPHERE;
            group(what, "center", 3, "x y z", o.center);
            at = cur_tok();
            group(what, "radius", 1, "r", &o.radius);
            if (!(o.radius > 0.0))
                fail_at(at->line, at->col, "sphere: radius %g must be positive", o.radius);
        } else {
            o.kind = kw == 2 ? K_PLANE : kw == 3 ? K_FPLANE : K_TPLANE;
            at = cur_tok();
            group(what, "normal", 3, "x y z", raw);
            unit_normal(&o, raw, at, what);
            group(what, "point", 3, "x y z", o.point);
            if (o.kind != K_PLANE) {
                const tok_t *oat = cur_tok(), *sat;
                group(what, o.kind == K_FPLANE ? "orient" : "xdir", 3, "x y z", o.orient);
                sat = cur_tok();
                group(what, o.kind == K_FPLANE ? "size" : "tile size", 2, "w h", o.size);
                if (!(o.size[0] > 0.0 && o.size[1] > 0.0))
                    fail_at(sat->line, sat->col, "%s: %s (%g, %g) must be positive", what,
                            o.kind == K_FPLANE ? "size" : "tile size", o.size[0], o.size[1]);
#ifdef TILE_NOPROJECT
                make_frame(&o, oat, what, o.kind != K_TPLANE);
#else
                make_frame(&o, oat, what, 1);
#endif
                if (o.kind == K_TPLANE)
                    read_mat(what, &o.bg, 1);
            }
        }
        read_extras(form, what);
        if (g_nobj == g_capobj) {
            g_capobj = g_capobj ? 2 * g_capobj : 16;
            g_obj = xrealloc(g_obj, g_capobj * sizeof(obj_t));
        }
        g_obj[g_nobj++] = o;
    }
}

static void parse_scene(void)
{
    if (g_ntok == 0)
        fail_at(1, 1, "empty scene file: expected the world window (w h), the viewpoint "
                "(x y z), then objects");
    g_numeric = detect_numeric();
    if (g_numeric) {
        int l;
        g_content = xrealloc(NULL, (g_nlines + 1) * sizeof(int));
        for (l = 0; l < g_nlines; l++)
            if (g_line_count[l])
                g_content[g_ncontent++] = l;
    }
    {
        const tok_t *at = cur_tok();
        group("header", "world window", 2, "w h", g_window);
        if (!(g_window[0] > 0.0 && g_window[1] > 0.0))
            fail_at(at->line, at->col, "header: world window (%g, %g) must be positive",
                    g_window[0], g_window[1]);
        group("header", "viewpoint", 3, "x y z", g_view);
    }
    if (!g_numeric) {
        while (g_pos < g_ntok) {
            const tok_t *t = &g_tok[g_pos];
            int kw = keyword_index(t);
            if (kw < 0) {
                if (unsupported_word(t))
                    fail_at(t->line, t->col, "%s is not supported (supported: pointlight, "
                            "sphere, plane, fplane, tplane)", show(t));
                fail_at(t->line, t->col, "expected an object keyword (pointlight, sphere, "
                        "plane, fplane, tplane), found %s'%s'", looks_number(t) ? "number " :
                        "unknown keyword ", show(t));
            }
            g_pos++;
            read_object(kw);
        }
    } else {
        while (g_pos < g_ncontent) {
            int l = g_content[g_pos], cnt = g_line_count[l], k, code, lead = 0, i;
            const tok_t *tk = g_tok + g_line_first[l];
            const tok_t *t = &tk[0];
            char b[16];
            int okint = t->len >= 1 && t->len <= 10;
            for (i = 0; okint && i < t->len; i++)
                if (!(isdigit((unsigned char)t->s[i]) ||
                      (i == 0 && (t->s[i] == '+' || t->s[i] == '-') && t->len > 1)))
                    okint = 0;
            if (!okint)
                fail_at(t->line, t->col, "expected an integer object code (10 point light, 13 "
                        "sphere, 14 plane, 15 finite plane, 16 tiled plane), found '%s'",
                        show(t));
            memcpy(b, t->s, t->len);
            b[t->len] = '\0';
            code = atoi(b);
            if (code == 9000 || code == 9001) {
                g_nflags++;
                g_pos++;
                continue;
            }
            for (k = 0; k < NFORMS && CODES[k] != code; k++)
                ;
            if (k == NFORMS) {
                if (code == 12 || (code >= 17 && code <= 29))
                    fail_at(t->line, t->col, "object code %d is not supported (supported: 10, "
                            "13, 14, 15, 16)", code);
                fail_at(t->line, t->col, "unknown object code %d; expected 10 point light, 13 "
                        "sphere, 14 plane, 15 finite plane or 16 tiled plane", code);
            }
            while (lead < cnt && num_syntax(&tk[lead]))
                lead++;
            /* a second number (nw's refraction index) is read and not used */
            g_pos++;
            read_object(k);
        }
    }
}

/* ------------------------------------------------------------------ hit functions */

typedef struct {
    double t;
    double hitloc[3];
    double newhit[3];   /* fplane/tplane: rotmat . (hitloc - point); .xy = lasthit */
} hit_t;

/* infinite plane: n.d == 0 misses; t = (n.P - n.base)/(n.d) must exceed TMIN; then the
 * screen clip on hitloc.z */
static int plane_hits(const obj_t *o, const double base[3], const double dir[3], hit_t *h)
{
    double nd = dot3(o->normal, dir), t, tmp[3];
    if (nd == 0.0)
        return 0;
    t = (dot3(o->normal, o->point) - dot3(o->normal, base)) / nd;
    if (!(t > TMIN))
        return 0;
    scale3(tmp, t, dir);
    sum3(h->hitloc, base, tmp);
    if (CLIPPED(h->hitloc[2]))
        return 0;
    h->t = t;
    return 1;
}

/* newhit = rotmat . (hitloc - point); with `in_place` the seed's literal
 * vl_xform3(newhit, rotmat, newhit), whose row 1 and 2 read the overwritten newhit[0] */
static void plane_coords(const obj_t *o, hit_t *h, int in_place)
{
    double newhit[3];
    diff3(newhit, h->hitloc, o->point);
    if (in_place) {
        xform3(newhit, (const double(*)[3])o->rotmat, newhit);
        memcpy(h->newhit, newhit, sizeof newhit);
    } else {
        xform3(h->newhit, (const double(*)[3])o->rotmat, newhit);
    }
}

#ifdef ALIAS_XFORM
#define FPLANE_IN_PLACE 1
#else
#define FPLANE_IN_PLACE 0
#endif

static int fplane_hits(const obj_t *o, const double base[3], const double dir[3], hit_t *h)
{
    double u, v;
    if (!plane_hits(o, base, dir, h))
        return 0;
    plane_coords(o, h, FPLANE_IN_PLACE);
    u = h->newhit[0];
    v = h->newhit[1];
#ifdef EDGES_OPEN
    if (!(u > 0.0 && u < o->size[0] && v > 0.0 && v < o->size[1]))
        return 0;
#else
    if (u > o->size[0] || u < 0.0)
        return 0;
    if (v > o->size[1] || v < 0.0)
        return 0;
#endif
    return 1;
}

static int tplane_hits(const obj_t *o, const double base[3], const double dir[3], hit_t *h)
{
    if (!plane_hits(o, base, dir, h))
        return 0;
    plane_coords(o, h, 0);      /* tile coordinates: always the correct transform */
    return 1;
}

/* a = d.d, b = 2 d.(base - c), c = |base - c|^2 - r^2; disc <= 0 misses; only the near root
 * (-b - sqrt(disc))/2a; t <= 0 misses (screen clip only with CLIP_SPHERES) */
static int sphere_hits(const obj_t *o, const double base[3], const double dir[3], hit_t *h)
{
    double oc[3], a, b, c, disc, t, tmp[3];
    diff3(oc, base, o->center);
    a = dot3(dir, dir);
    b = 2.0 * dot3(dir, oc);
    c = dot3(oc, oc) - o->radius * o->radius;
    disc = b * b - 4.0 * a * c;
    if (!(disc > 0.0))
        return 0;
    t = (-b - sqrt(disc)) / (2.0 * a);
    if (!(t > 0.0))
        return 0;
    scale3(tmp, t, dir);
    sum3(h->hitloc, base, tmp);
#ifdef CLIP_SPHERES
    if (CLIPPED(h->hitloc[2]))
        return 0;
#endif
    h->t = t;
    return 1;
}

static int hits(const obj_t *o, const double base[3], const double dir[3], hit_t *h)
{
    switch (o->kind) {
    case K_SPHERE: return sphere_hits(o, base, dir, h);
    case K_PLANE: return plane_hits(o, base, dir, h);
    case K_FPLANE: return fplane_hits(o, base, dir, h);
    default: return tplane_hits(o, base, dir, h);
    }
}

/* closest hit with t > 0 (each hit function applies its own threshold), ignoring object
 * `skip` (-1: none).  Exact tie: the earlier object wins (TIES_LAST: the later one). */
static int find_closest(const double base[3], const double dir[3], int skip, hit_t *best)
{
    int i, won = -1;
    hit_t h;
    for (i = 0; i < g_nobj; i++) {
        if (i == skip || !hits(&g_obj[i], base, dir, &h))
            continue;
#ifdef TIES_LAST
        if (won < 0 || h.t <= best->t) {
#else
        if (won < 0 || h.t < best->t) {
#endif
            *best = h;
            won = i;
        }
    }
    return won;
}

#ifndef NO_SHADOWS
/* is any object but `self` hit along dir closer than dist? */
static int shadowed(const double base[3], const double dir[3], double dist, int self)
{
    int i;
    hit_t h;
    for (i = 0; i < g_nobj; i++)
        if (i != self && hits(&g_obj[i], base, dir, &h) && h.t < dist)
            return 1;
    return 0;
}
#endif

/* ------------------------------------------------------------------ shading */

static int g_capped;

/* One shaded hit of a ray path: its own intensity I_k (already divided) and its specular. */
typedef struct {
    double I[3], spec[3];
} level_t;

static level_t *g_lv;
static long g_caplv;

/* The notes' trace(base, dir, total_dist, skip) for the primary ray; the recursion
 *   I = local(hit) + specular (.) trace(H, R, total_dist, skip = O)
 * is unrolled into a list of levels and summed back from the deepest one, so the arithmetic
 * is exactly the recursion's (I_k + s_k * (I_k+1 + s_k+1 * (...))), without its stack depth.
 * Returns the primary hit (object id, -1 on a miss) and its t. */
static int trace(const double base0[3], const double dir0[3], double out[3], double *t0)
{
    double base[3], dir[3], total_dist = 0.0;
    int skip = -1, first = -2;
    long n = 0, k;
    memcpy(base, base0, sizeof base);
    memcpy(dir, dir0, sizeof dir);
    *t0 = 0.0;
    for (;;) {
        hit_t h;
        const obj_t *o;
        const mat_t *m;
        double N[3], I[3];
        int id, li, c3;
        memset(&h, 0, sizeof h);
        id = find_closest(base, dir, skip, &h);
        if (first == -2) {
            first = id;
            *t0 = id >= 0 ? h.t : 0.0;
        }
        if (id < 0)
            break;
        o = &g_obj[id];
        total_dist += h.t;
        m = &o->mat;
        if (o->kind == K_TPLANE) {
#ifdef TILE_ADD_FIRST
            double relx = floor((TILE_OFF + h.newhit[0]) / o->size[0]);
            double rely = floor((TILE_OFF + h.newhit[1]) / o->size[1]);
#else
            double relx = floor(TILE_OFF + h.newhit[0] / o->size[0]);
            double rely = floor(TILE_OFF + h.newhit[1] / o->size[1]);
#endif
#ifdef TILE_SWAP
            if (fmod(relx + rely, 2.0) != 0.0)  /* the bug: the colours swapped */
#else
            if (fmod(relx + rely, 2.0) == 0.0)
#endif
                m = &o->bg;                 /* even: background; odd: foreground */
        }
        if (o->kind == K_SPHERE) {
            double tmp[3];
            diff3(tmp, h.hitloc, o->center);
            unit3(N, tmp);
        } else {
            memcpy(N, o->normal, sizeof N);
        }
#ifdef AMB_AFTER
        memset(I, 0, sizeof I);             /* the bug: ambient added after dividing */
#else
        memcpy(I, m->amb, sizeof I);
#endif
        for (li = 0; li < g_nlight; li++) {
            const light_t *L = &g_light[li];
            double D[3], U[3], d, c;
            diff3(D, L->center, h.hitloc);
            d = length3(D);
            unit3(U, D);
            c = dot3(U, N);
            if (c <= 0.0)
                continue;                   /* light behind the surface */
            if (L->spot) {                  /* outside the spotlight's cone */
                double S[3], US[3];
                diff3(S, h.hitloc, L->center);
                unit3(US, S);
                if (!(dot3(US, L->axis) > L->cos_theta))
                    continue;
            }
#ifndef NO_SHADOWS
#ifdef SELF_SHADOW
            if (shadowed(h.hitloc, U, d, -1))   /* the bug: may hit its own surface */
#else
            if (shadowed(h.hitloc, U, d, id))
#endif
                continue;
#endif
            for (c3 = 0; c3 < 3; c3++)
#ifdef INV_SQUARE
                I[c3] += m->dif[c3] * L->emis[c3] * c / (d * d);
#else
                I[c3] += m->dif[c3] * L->emis[c3] * c / d;
#endif
        }
        for (c3 = 0; c3 < 3; c3++)
#ifdef REFLECT_SEGMENT
            I[c3] /= h.t;
#else
            I[c3] /= total_dist;
#endif
#ifdef AMB_AFTER
        for (c3 = 0; c3 < 3; c3++)
            I[c3] += m->amb[c3];
#endif
        if (n == g_caplv) {
            g_caplv = g_caplv ? 2 * g_caplv : 64;
            g_lv = xrealloc(g_lv, g_caplv * sizeof(level_t));
        }
        memcpy(g_lv[n].I, I, sizeof I);
        memcpy(g_lv[n].spec, m->spec, sizeof I);
        n++;
        if (!(m->spec[0] != 0.0 || m->spec[1] != 0.0 || m->spec[2] != 0.0))
            break;
        if (!(total_dist < MAX_DIST))
            break;
        if (n > MAX_BOUNCES) {
            g_capped = 1;
            break;
        }
        {   /* R = reflect(dir, N) = dir - 2 (dir.N) N, made unit; from H, skipping O */
            double R[3], tmp[3];
            scale3(tmp, 2.0 * dot3(dir, N), N);
            diff3(R, dir, tmp);
            unit3(dir, R);
            memcpy(base, h.hitloc, sizeof base);
            skip = id;
        }
    }
    out[0] = out[1] = out[2] = 0.0;   /* a miss (also of a reflected ray) adds nothing */
    for (k = n - 1; k >= 0; k--) {
        int c3;
        for (c3 = 0; c3 < 3; c3++)
            out[c3] = g_lv[k].I[c3] + g_lv[k].spec[c3] * out[c3];
    }
    return first;
}

static unsigned char quant(double I)
{
    if (!(I > 0.0))
        return 0;                       /* also NaN */
#ifdef CLAMP_AFTER
    if (I < 1e9)                        /* the bug: no clamp, the byte wraps around */
        return (unsigned char)(long)(255.0 * I);
#endif
    if (I > 1.0)
        I = 1.0;
#ifdef QUANT_ROUND
    return (unsigned char)floor(255.0 * I + 0.5);   /* the bug: rounds, the notes floor */
#else
    return (unsigned char)floor(255.0 * I);
#endif
}

/* ------------------------------------------------------------------ main */

static void usage(const char *msg)
{
    fprintf(stderr, "course: %s; usage: course COLUMNS [ROWS] [--hits FILE] < scene > out.ppm\n",
            msg);
    exit(64);
}

static long parse_count(const char *s, const char *what)
{
    char *end;
    long v = strtol(s, &end, 10);
    if (*s == '\0' || *end != '\0' || v < 1 || v > 1000000)
        usage(what);
    return v;
}

int main(int argc, char **argv)
{
    long W = -1, H = -1, npix, i;
    const char *hits_path = NULL;
    FILE *hf = NULL;
    unsigned char *img;
    int a, x, r;

    for (a = 1; a < argc; a++) {
        if (strcmp(argv[a], "--hits") == 0) {
            if (a + 1 >= argc)
                usage("--hits needs a file name");
            hits_path = argv[++a];
        } else if (W < 0) {
            W = parse_count(argv[a], "COLUMNS must be an integer 1..1000000");
        } else if (H < 0) {
            H = parse_count(argv[a], "ROWS must be an integer 1..1000000");
        } else {
            usage("too many arguments");
        }
    }
    if (W < 0)
        usage("COLUMNS is missing");

    read_input();
    parse_scene();

    if (H < 0)
        H = (long)(g_window[1] / g_window[0] * (double)W);
    if (W < 2 || H < 2) {
        fprintf(stderr, "course: image %ldx%ld is too small: corner sampling needs at least 2 "
                "columns and rows\n", W, H);
        exit(64);
    }
    if (W * H > 100000000L)
        usage("image too large");
    npix = W * H;
    img = xrealloc(NULL, (size_t)npix * 3);
    if (hits_path) {
        hf = fopen(hits_path, "w");
        if (!hf) {
            fprintf(stderr, "course: cannot write %s\n", hits_path);
            exit(1);
        }
    }

    for (r = 0; r < H; r++) {               /* image row r, top first */
#ifdef ROWS_SHIFTED
        long y = H - r;                      /* the bug: one row too high */
#elif defined(ROWS_FLIPPED)
        long y = r;                          /* the bug: the bottom row written first */
#else
        long y = H - 1 - r;                  /* course row, 0 = bottom */
#endif
#ifdef OFF_BY_ONE
        double wy = (double)y / (double)H * g_window[1] - g_window[1] / 2.0;   /* the bug */
#else
        double wy = (double)y / (double)(H - 1) * g_window[1] - g_window[1] / 2.0;
#endif
        for (x = 0; x < W; x++) {
            double world[3], dir[3], tmp[3], I[3], t;
            int id;
#ifdef OFF_BY_ONE
            world[0] = (double)x / (double)W * g_window[0] - g_window[0] / 2.0;
#else
            world[0] = (double)x / (double)(W - 1) * g_window[0] - g_window[0] / 2.0;
#endif
            world[1] = wy;
            world[2] = 0.0;
            diff3(tmp, world, g_view);
#ifdef DIR_NOT_UNIT
            dir[0] = tmp[0], dir[1] = tmp[1], dir[2] = tmp[2];   /* the bug: not a unit */
#else
            unit3(dir, tmp);
#endif
            id = trace(g_view, dir, I, &t);
            i = ((long)r * W + x) * 3;
            img[i] = quant(I[0]);
            img[i + 1] = quant(I[1]);
            img[i + 2] = quant(I[2]);
            if (hf)
                fprintf(hf, "%d %d %d %.17g\n", x, r, id, id >= 0 ? t : 0.0);
        }
    }
    if (g_capped)
        fprintf(stderr, "course: warning: reflection stopped at MAX_BOUNCES=%ld before "
                "MAX_DIST\n", (long)MAX_BOUNCES);
    if (hf && fclose(hf) != 0) {
        fprintf(stderr, "course: cannot write %s\n", hits_path);
        exit(1);
    }
#ifdef HDR_256
    printf("P6\n%ld %ld\n256\n", W, H);      /* the bug: 256 means two-byte samples */
#else
    printf("P6\n%ld %ld\n255\n", W, H);
#endif
    if (fwrite(img, 3, (size_t)npix, stdout) != (size_t)npix || fflush(stdout) != 0) {
        fprintf(stderr, "course: cannot write the image\n");
        exit(1);
    }
    free(img);
    return 0;
}
