/* First occupied leaf along each ray of a sparse voxel octree, on the CPU.
 *
 * The same traversal as voxnerf.octree.SparseVoxelOctree.first_hit's PyTorch path, one ray at a time: a node's
 * segment [t0, t1] is split at its three mid-planes into at most 4 consecutive child segments, in the same
 * float32 arithmetic (plane - origin) / dir, min/max and clamp, so the distances agree bit for bit. Children are
 * visited depth first, front to back, so the first leaf reached is the nearest and the ray stops there.
 * Built and loaded by voxnerf/native.py; plain C and POSIX threads.
 *
 * Shapes: origins, dirs [n, 3] (dirs with no zero component), t0, t1 [n] (each ray's segment inside the root;
 * rays with !(t0 < t1) miss), first_slot [n] (the child slot x | y << 1 | z << 2 a ray enters first: the octant
 * opposite its direction), planes[l] [3, nodes_l] (mid-planes), child_index[l] [8 * nodes_l] (index of each
 * child in level l + 1, or -1), for l = 0 .. levels - 1. Writes t_hit [n]: the entry of the first hit leaf, or
 * +inf.
 */
#include <math.h>
#include <pthread.h>
#include <stdint.h>

#define MAX_LEVELS 21
#define MAX_THREADS 64
#define STACK (3 * MAX_LEVELS + 2) /* each level pops one node and pushes at most 4 */
#define CHUNK 256                 /* rays handed out together to a thread */

typedef struct {
    const float *origins, *dirs, *t0, *t1;
    const int32_t *first_slot;
    const float *const *planes;
    const int32_t *const *child_index;
    const int64_t *nodes;
    int levels;
    int64_t n;
    float *t_hit;
    int thread, threads;
} job_t;

static inline float min_f(float a, float b) { return b < a ? b : a; } /* torch.minimum for non-NaN values */
static inline float max_f(float a, float b) { return b > a ? b : a; }

typedef struct {
    int level;
    int32_t node;
    float t0, t1;
} entry_t;

static float trace(const job_t *j, int64_t r) {
    const float o[3] = {j->origins[3 * r], j->origins[3 * r + 1], j->origins[3 * r + 2]};
    const float d[3] = {j->dirs[3 * r], j->dirs[3 * r + 1], j->dirs[3 * r + 2]};
    const int32_t slot = j->first_slot[r];
    entry_t stack[STACK];
    int top = 0;
    if (!(j->t0[r] < j->t1[r])) return INFINITY;
    stack[top++] = (entry_t){0, 0, j->t0[r], j->t1[r]};
    while (top > 0) {
        const entry_t e = stack[--top];
        const float *planes = j->planes[e.level];
        const int64_t m = j->nodes[e.level];
        const float x = (planes[e.node] - o[0]) / d[0];
        const float y = (planes[m + e.node] - o[1]) / d[1];
        const float z = (planes[2 * m + e.node] - o[2]) / d[2];
        const float lo_xy = min_f(x, y), hi_xy = max_f(x, y);
        float b[5] = {e.t0, min_f(lo_xy, z), max_f(lo_xy, min_f(hi_xy, z)), max_f(hi_xy, z), e.t1};
        for (int k = 1; k < 4; k++) b[k] = min_f(max_f(b[k], e.t0), e.t1);
        /* Child slots in the order the ray enters them: the first octant, then the earliest-crossed axis flipped,
         * then all but the latest, then all three (ties ordered z < y < x, giving zero-length segments). */
        const int xy = x < y, yz = y < z, xz = x < z;
        const int first_x = xy & xz, first_y = yz & !xy;
        const int last_x = !(xy | xz), last_y = xy & !yz;
        const int32_t key0 = e.node * 8 + slot;
        const int32_t key3 = key0 ^ 7;
        const int32_t keys[4] = {key0, key0 ^ (first_x | first_y << 1 | !(first_x | first_y) << 2),
                                 key3 ^ (last_x | last_y << 1 | !(last_x | last_y) << 2), key3};
        const int32_t *children = j->child_index[e.level];
        if (e.level == j->levels - 1) {
            for (int k = 0; k < 4; k++)
                if (children[keys[k]] >= 0 && b[k] < b[k + 1]) return b[k];
            continue;
        }
        for (int k = 3; k >= 0; k--) /* pushed back to front: the nearest child is popped first */
            if (children[keys[k]] >= 0 && b[k] < b[k + 1])
                stack[top++] = (entry_t){e.level + 1, children[keys[k]], b[k], b[k + 1]};
    }
    return INFINITY;
}

static void *trace_rays(void *arg) {
    const job_t *j = (const job_t *)arg;
    for (int64_t c = (int64_t)j->thread * CHUNK; c < j->n; c += (int64_t)j->threads * CHUNK) {
        const int64_t end = c + CHUNK < j->n ? c + CHUNK : j->n;
        for (int64_t r = c; r < end; r++) j->t_hit[r] = trace(j, r);
    }
    return NULL;
}

void octree_first_hit(const float *origins, const float *dirs, const float *t0, const float *t1,
                      const int32_t *first_slot, const float *const *planes, const int32_t *const *child_index,
                      const int64_t *nodes, int levels, int64_t n, float *t_hit, int threads) {
    if (threads < 1) threads = 1;
    if (threads > MAX_THREADS) threads = MAX_THREADS;
    if (levels < 1 || levels > MAX_LEVELS) return;
    job_t jobs[MAX_THREADS];
    pthread_t ids[MAX_THREADS];
    int started[MAX_THREADS] = {0};
    for (int i = 0; i < threads; i++)
        jobs[i] = (job_t){origins, dirs, t0, t1, first_slot, planes, child_index, nodes, levels, n, t_hit, i, threads};
    for (int i = 1; i < threads; i++) started[i] = pthread_create(&ids[i], NULL, trace_rays, &jobs[i]) == 0;
    trace_rays(&jobs[0]);
    for (int i = 1; i < threads; i++) {
        if (started[i]) pthread_join(ids[i], NULL);
        else trace_rays(&jobs[i]);
    }
}
