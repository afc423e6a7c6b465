/* Multi-resolution hash encoding on the CPU: forward (gather + trilinear blend) and the table's gradient.
 *
 * The same arithmetic as voxnerf.field.HashEncoding (float32 positions, int32 cells, uint32 hashing with
 * instant-ngp's primes, dense indexing of the coarse levels, blend z then y then x). Work is split by level:
 * each thread owns whole levels, so the backward adds into its own slice of the gradient table without
 * atomics, and one level's slice (2^17 x 2 floats = 1 MB at the cpu preset) stays in cache while it is
 * written. Built and loaded by voxnerf/hash_kernel.py; plain C and POSIX threads, no Python or torch headers.
 *
 * Shapes: x [n, 3] in [0, 1] (clamped here), table and grad_table [levels * table_size, features],
 * out [n, levels, features] (the layout the MLP reads), grad_out [levels, n, features] (level-major: a level's
 * pass reads one stream and leaves the cache to the table), resolution [levels] (float), all contiguous,
 * row-major. Within a level, the corners of a block of points are computed and prefetched before their rows
 * are read, so the random reads overlap.
 */
#include <pthread.h>
#include <stdint.h>
#include <string.h>

#define MAX_THREADS 64
#define BLOCK 64 /* points whose corners are computed (and prefetched) before their features are read */

#if defined(__x86_64__) && (defined(__GNUC__) || defined(__clang__))
#define VECTOR_CLONES __attribute__((target_clones("avx512f", "avx2", "default")))
#else
#define VECTOR_CLONES
#endif

typedef struct {
    const float *x;
    int64_t n;
    const float *table;     /* forward only */
    float *out;             /* forward only */
    const float *grad_out;  /* backward only */
    float *grad_table;      /* backward only */
    float *grad_x;          /* position backward only */
    int levels, features, dense_levels, first_level, level_step;
    int64_t table_size;
    const float *resolution;
} job_t;

/* The 8 corner rows (level offset included) and the 3 blend fractions of point p at level l. */
static inline void corners(const job_t *j, int l, int64_t p, int64_t rows[8], float frac[3]) {
    const float res = j->resolution[l];
    const int32_t max_cell = (int32_t)res - 1;
    int32_t cell[3];
    for (int a = 0; a < 3; a++) {
        float v = j->x[p * 3 + a];
        v = v > 0.0f ? (v < 1.0f ? v : 1.0f) : 0.0f; /* NaN -> 0: never an index outside the table */
        const float pos = v * res;
        int32_t c = (int32_t)pos; /* pos >= 0: truncation is floor, without a libm call */
        if (c > max_cell) c = max_cell;
        frac[a] = pos - (float)c;
        cell[a] = c;
    }
    const int64_t base = (int64_t)l * j->table_size;
    if (l < j->dense_levels) {
        const int64_t s1 = (int64_t)res + 1, s2 = s1 * s1;
        for (int k = 0; k < 8; k++)
            rows[k] = base + (cell[0] + (k >> 2)) + (cell[1] + ((k >> 1) & 1)) * s1 + (cell[2] + (k & 1)) * s2;
    } else {
        const uint32_t mask = (uint32_t)(j->table_size - 1);
        for (int k = 0; k < 8; k++) {
            const uint32_t hx = (uint32_t)(cell[0] + (k >> 2));
            const uint32_t hy = (uint32_t)(cell[1] + ((k >> 1) & 1)) * 2654435761u;
            const uint32_t hz = (uint32_t)(cell[2] + (k & 1)) * 805459861u;
            rows[k] = base + (int64_t)((hx ^ hy ^ hz) & mask);
        }
    }
}

/* Corners and fractions of the block of points p0 .. p0 + BLOCK - 1 (fewer at the end; returns how many) at
 * level l, with their rows of `target` prefetched (for writing when `write`), so the block's loads overlap. */
static inline int block_corners(const job_t *j, int l, int64_t p0, const float *target, int write,
                                int64_t rows[BLOCK][8], float t[BLOCK][3]) {
    const int nb = j->n - p0 < BLOCK ? (int)(j->n - p0) : BLOCK;
    for (int i = 0; i < nb; i++) {
        corners(j, l, p0 + i, rows[i], t[i]);
        for (int k = 0; k < 8; k++) {
            if (write) __builtin_prefetch(target + rows[i][k] * j->features, 1, 3);
            else __builtin_prefetch(target + rows[i][k] * j->features, 0, 3);
        }
    }
    return nb;
}

/* The forward pass works on blocks of points in struct-of-arrays form (cells, fractions, then the 8 corner
 * rows of every point) so the compiler vectorises each step; on x86-64 it is compiled for AVX-512, AVX2 and the
 * baseline, and the loader picks the best the CPU has. The arithmetic is the same whichever runs. */
VECTOR_CLONES static void *forward_levels(void *arg) {
    const job_t *j = (const job_t *)arg;
    const int f = j->features;
    float t[3][BLOCK];
    uint32_t cell[3][BLOCK], idx[8][BLOCK];
    for (int l = j->first_level; l < j->levels; l += j->level_step) {
        const float res = j->resolution[l];
        const int32_t max_cell = (int32_t)res - 1;
        const float *tab = j->table + (int64_t)l * j->table_size * f;
        const uint32_t s1 = (uint32_t)res + 1, s2 = s1 * s1, mask = (uint32_t)(j->table_size - 1);
        const int dense = l < j->dense_levels;
        for (int64_t p0 = 0; p0 < j->n; p0 += BLOCK) {
            const int nb = j->n - p0 < BLOCK ? (int)(j->n - p0) : BLOCK;
            const float *x = j->x + p0 * 3;
            for (int a = 0; a < 3; a++) {
                for (int i = 0; i < nb; i++) {
                    float v = x[i * 3 + a];
                    v = v > 0.0f ? (v < 1.0f ? v : 1.0f) : 0.0f; /* NaN -> 0: never outside the table */
                    const float pos = v * res;
                    int32_t c = (int32_t)pos; /* pos >= 0: truncation is floor */
                    c = c > max_cell ? max_cell : c;
                    t[a][i] = pos - (float)c;
                    cell[a][i] = (uint32_t)c;
                }
            }
            if (dense) {
                for (int k = 0; k < 8; k++)
                    for (int i = 0; i < nb; i++)
                        idx[k][i] = (cell[0][i] + (k >> 2)) + (cell[1][i] + ((k >> 1) & 1)) * s1 +
                                    (cell[2][i] + (k & 1)) * s2;
            } else {
                for (int k = 0; k < 8; k++)
                    for (int i = 0; i < nb; i++)
                        idx[k][i] = ((cell[0][i] + (k >> 2)) ^ (cell[1][i] + ((k >> 1) & 1)) * 2654435761u ^
                                     (cell[2][i] + (k & 1)) * 805459861u) & mask;
            }
            for (int i = 0; i < nb; i++)
                for (int k = 0; k < 8; k++) __builtin_prefetch(tab + (int64_t)idx[k][i] * f, 0, 3);
            for (int c = 0; c < f; c++) {
                for (int i = 0; i < nb; i++) {
                    float v[8];
                    for (int k = 0; k < 8; k++) v[k] = tab[(int64_t)idx[k][i] * f + c];
                    float yz[4];
                    for (int k = 0; k < 4; k++) yz[k] = v[2 * k] + (v[2 * k + 1] - v[2 * k]) * t[2][i];
                    const float z0 = yz[0] + (yz[1] - yz[0]) * t[1][i];
                    const float z1 = yz[2] + (yz[3] - yz[2]) * t[1][i];
                    j->out[((p0 + i) * (int64_t)j->levels + l) * f + c] = z0 + (z1 - z0) * t[0][i];
                }
            }
        }
    }
    return NULL;
}

static void *backward_levels(void *arg) {
    const job_t *j = (const job_t *)arg;
    const int f = j->features;
    int64_t rows[BLOCK][8];
    float t[BLOCK][3];
    for (int l = j->first_level; l < j->levels; l += j->level_step) {
        memset(j->grad_table + (int64_t)l * j->table_size * f, 0, sizeof(float) * (size_t)(j->table_size * f));
        for (int64_t p0 = 0; p0 < j->n; p0 += BLOCK) {
            const int nb = block_corners(j, l, p0, j->grad_table, 1, rows, t);
            for (int i = 0; i < nb; i++) {
                const float *g = j->grad_out + ((int64_t)l * j->n + p0 + i) * f;
                const float wx[2] = {1.0f - t[i][0], t[i][0]}, wy[2] = {1.0f - t[i][1], t[i][1]},
                            wz[2] = {1.0f - t[i][2], t[i][2]};
                for (int k = 0; k < 8; k++) {
                    const float w = wx[k >> 2] * wy[(k >> 1) & 1] * wz[k & 1];
                    float *dst = j->grad_table + rows[i][k] * f;
                    for (int c = 0; c < f; c++) dst[c] += w * g[c];
                }
            }
        }
    }
    return NULL;
}

/* The gradient of the positions: grad_x[p] = sum over levels and features of grad_out[p, l, c] times the
 * derivative of the trilinear blend in each axis, res * (upper face - lower face). A clamped coordinate (outside
 * [0, 1]) gets none, as through torch.clamp. Points are split between threads in contiguous ranges (here
 * first_level and level_step number the thread and the threads), each point summing over every level, so no
 * two threads write the same row; a block of points at a time, its corners prefetched level by level.
 * grad_out is point-major here [n, levels, features]. */
static void *backward_x_points(void *arg) {
    const job_t *j = (const job_t *)arg;
    const int f = j->features;
    int64_t rows[BLOCK][8];
    float t[BLOCK][3], gx[BLOCK][3];
    const int64_t chunk = (j->n + j->level_step - 1) / j->level_step;
    const int64_t begin = j->first_level * chunk;
    const int64_t end = begin + chunk < j->n ? begin + chunk : j->n;
    job_t range = *j;
    range.n = end; /* block_corners stops at the range's end */
    for (int64_t p0 = begin; p0 < end; p0 += BLOCK) {
        int nb = 0;
        memset(gx, 0, sizeof(gx));
        for (int l = 0; l < j->levels; l++) {
            nb = block_corners(&range, l, p0, j->table, 0, rows, t);
            const float res = j->resolution[l];
            for (int i = 0; i < nb; i++) {
                const float *g = j->grad_out + ((p0 + i) * j->levels + l) * f;
                float dx = 0.0f, dy = 0.0f, dz = 0.0f;
                for (int c = 0; c < f; c++) {
                    float v[8], yz[4], dyz[4];
                    for (int k = 0; k < 8; k++) v[k] = j->table[rows[i][k] * f + c];
                    for (int k = 0; k < 4; k++) {
                        yz[k] = v[2 * k] + (v[2 * k + 1] - v[2 * k]) * t[i][2];
                        dyz[k] = v[2 * k + 1] - v[2 * k];
                    }
                    const float z0 = yz[0] + (yz[1] - yz[0]) * t[i][1], z1 = yz[2] + (yz[3] - yz[2]) * t[i][1];
                    const float dz0 = dyz[0] + (dyz[1] - dyz[0]) * t[i][1];
                    const float dz1 = dyz[2] + (dyz[3] - dyz[2]) * t[i][1];
                    dx += g[c] * (z1 - z0);
                    dy += g[c] * ((1.0f - t[i][0]) * (yz[1] - yz[0]) + t[i][0] * (yz[3] - yz[2]));
                    dz += g[c] * (dz0 + (dz1 - dz0) * t[i][0]);
                }
                gx[i][0] += dx * res;
                gx[i][1] += dy * res;
                gx[i][2] += dz * res;
            }
        }
        for (int i = 0; i < nb; i++)
            for (int a = 0; a < 3; a++) {
                const float v = j->x[(p0 + i) * 3 + a];
                j->grad_x[(p0 + i) * 3 + a] = (v >= 0.0f && v <= 1.0f) ? gx[i][a] : 0.0f;
            }
    }
    return NULL;
}

static void run(job_t *proto, int threads, void *(*fn)(void *)) {
    if (threads < 1) threads = 1;
    if (threads > proto->levels && fn != backward_x_points) threads = proto->levels;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    job_t jobs[MAX_THREADS];
    pthread_t ids[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int i = 0; i < threads; i++) {
        jobs[i] = *proto;
        jobs[i].first_level = i;
        jobs[i].level_step = threads;
    }
    for (int i = 1; i < threads; i++) started[i] = pthread_create(&ids[i], NULL, fn, &jobs[i]) == 0;
    fn(&jobs[0]);
    for (int i = 1; i < threads; i++) {
        if (started[i]) pthread_join(ids[i], NULL);
        else fn(&jobs[i]); /* no thread to be had: do that share here */
    }
}

void hash_encode_forward(const float *x, int64_t n, const float *table, int levels, int features,
                         int64_t table_size, int dense_levels, const float *resolution, float *out, int threads) {
    job_t j = {x, n, table, out, NULL, NULL, NULL, levels, features, dense_levels, 0, 1, table_size, resolution};
    run(&j, threads, forward_levels);
}

/* grad_table is overwritten (each thread zeroes its own levels first). */
void hash_encode_backward(const float *x, int64_t n, const float *grad_out, int levels, int features,
                          int64_t table_size, int dense_levels, const float *resolution, float *grad_table,
                          int threads) {
    job_t j = {x, n, NULL, NULL, grad_out, grad_table, NULL, levels, features, dense_levels, 0, 1, table_size,
               resolution};
    run(&j, threads, backward_levels);
}

/* grad_x [n, 3] is overwritten; grad_out is point-major [n, levels, features]. */
void hash_encode_backward_x(const float *x, int64_t n, const float *table, const float *grad_out, int levels,
                            int features, int64_t table_size, int dense_levels, const float *resolution,
                            float *grad_x, int threads) {
    job_t j = {x, n, table, NULL, grad_out, NULL, grad_x, levels, features, dense_levels, 0, 1, table_size,
               resolution};
    run(&j, threads, backward_x_points);
}
