// The weld and the edge ids on the device, with exactly the numbering of the numpy path (gpuslice.mesh):
// equal keys share an id, and ids are numbered 0, 1, ... in the order the distinct keys first occur.
//
// Keys: a corner's three float32 bit patterns (weld), or the undirected vertex pair (min, max) of a facet side
// (edges; side k of facet f is item 3f + k and joins corners k and (k + 1) % 3).
//
// One open-addressing table of `mask + 1` int slots (a power of two, more slots than keys), every slot -1 (empty):
//   1. weld_insert_*: each item hashes its key and probes linearly; an empty slot is claimed with
//      atomic_cmpxchg(-1, i); a taken slot holds some item with the same key or another key (compared exactly, bit
//      for bit). Once a slot is taken its key never changes, so an item that finds its key lowers the slot to its
//      own index with atomic_min: at the end of the pass the slot holds the SMALLEST index with that key, whatever
//      order the work-items ran in. slot_of[i] remembers the slot.
//   2. weld_count_firsts: item i is the first of its key iff slots[slot_of[i]] == i: a flag per item, and a count per
//      chunk of `chunk` consecutive items.
//   3. weld_scan_counts: one work-group turns the chunk counts into exclusive offsets and the total (number of ids).
//   4. weld_emit_*: each chunk walks its flags in order; the k-th first overall gets id k, its slot is overwritten
//      with that id, and the per-id output (the first index, or the edge's two vertices) is written.
//   5. weld_gather_ids: ids[i] = slots[slot_of[i]] (weld_gather_sides also counts each edge's sides, its forward
//      sides, and keeps its last one: the pairing of the mesh check).
// Kernel boundaries order the passes; only 32-bit atomics of OpenCL 1.2 core are used.

#ifndef LOCAL_SIZE
#define LOCAL_SIZE 64
#endif

#define WELD_EMPTY (-1)

// a 32-bit finaliser (good avalanche, invertible)
inline uint weld_mix32(uint h) {
    h ^= h >> 16;
    h *= 0x7feb352dU;
    h ^= h >> 15;
    h *= 0x846ca68bU;
    h ^= h >> 16;
    return h;
}

inline uint weld_corner_hash(const uint x, const uint y, const uint z) {
    uint h = weld_mix32(x + 0x9e3779b9U);
    h = weld_mix32(h ^ (y + 0x632be59bU));
    return weld_mix32(h ^ (z + 0x8cb92ba7U));
}

inline uint weld_edge_hash(const uint lo, const uint hi) {
    return weld_mix32(weld_mix32(lo + 0x9e3779b9U) ^ (hi + 0x632be59bU));
}

// the vertex pair (min, max) of side s = 3f + k
inline int2 weld_side_key(__global const int *faces, const int s) {
    const int k = s % 3;
    const int a = faces[s], b = faces[k == 2 ? s - 2 : s + 1];
    return (int2)(min(a, b), max(a, b));
}

// corner i's coordinate k as bits; with zero == 0x80000000 (else 0), -0.0 is read as 0.0 (so both weld together)
inline uint weld_coord(__global const uint *corners, const int i, const int k, const uint zero) {
    const uint b = corners[3 * i + k];
    return b == zero ? 0U : b;
}

// Pass 1 for corners: claim or find the slot of corner i's bit-identical coordinates (-0.0 as 0.0 if zero says so).
// hash_and is ANDed into the hash (0xffffffff normally; tests use a few bits to force long collision chains).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_insert_corners(__global const uint *corners, const int n, volatile __global int *slots, const uint mask,
                    const uint hash_and, const uint zero, __global int *slot_of) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const uint x = weld_coord(corners, i, 0, zero), y = weld_coord(corners, i, 1, zero);
    const uint z = weld_coord(corners, i, 2, zero);
    uint s = weld_corner_hash(x, y, z) & hash_and & mask;
    for (;;) {
        const int v = atomic_cmpxchg(&slots[s], WELD_EMPTY, i);
        if (v == WELD_EMPTY) break;  // claimed
        // v: an item already in the slot; the slot keeps its key, though v may since have been lowered
        if (weld_coord(corners, v, 0, zero) == x && weld_coord(corners, v, 1, zero) == y
            && weld_coord(corners, v, 2, zero) == z) {
            if (i < v) atomic_min(&slots[s], i);
            break;
        }
        s = (s + 1) & mask;
    }
    slot_of[i] = (int)s;
}

// Pass 1 for facet sides: the same with the key (min, max) of the side's two vertex ids. The first probe is
// lo * spread + (a hash of hi) % spread (spread: a power of two, about slots / vertices): vertex ids are numbered by
// first occurrence, so the sides of nearby facets probe nearby slots (cache friendly; 3-4x faster on a CPU than a
// scattering hash on large meshes). Collisions only lengthen the probe; the result never depends on the hash.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_insert_sides(__global const int *faces, const int n, volatile __global int *slots, const uint mask,
                  const uint hash_and, const uint spread, __global int *slot_of) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int2 key = weld_side_key(faces, i);
    uint s = ((uint)key.x * spread + (weld_mix32((uint)key.y) & (spread - 1u))) & hash_and & mask;
    for (;;) {
        const int v = atomic_cmpxchg(&slots[s], WELD_EMPTY, i);
        if (v == WELD_EMPTY) break;
        const int2 other = weld_side_key(faces, v);
        if (other.x == key.x && other.y == key.y) {
            if (i < v) atomic_min(&slots[s], i);
            break;
        }
        s = (s + 1) & mask;
    }
    slot_of[i] = (int)s;
}

// Pass 2: work-item c flags and counts the firsts among items [c * chunk, (c + 1) * chunk).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_count_firsts(__global const int *slots, __global const int *slot_of, const int n, const int chunk,
                  const int n_chunks, __global uchar *is_first, __global int *counts) {
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(n, lo + chunk);
    int count = 0;
    for (int i = lo; i < hi; ++i) {
        const int f = slots[slot_of[i]] == i;
        is_first[i] = (uchar)f;
        count += f;
    }
    counts[c] = count;
}

// Pass 3, one work-group: offsets = exclusive prefix sum of counts; total[0] = the sum.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_scan_counts(__global const int *counts, const int n_chunks, __global int *offsets, __global int *total) {
    __local int part[LOCAL_SIZE];
    const int l = get_local_id(0);
    const int per = (n_chunks + LOCAL_SIZE - 1) / LOCAL_SIZE;
    const int lo = min(n_chunks, l * per), hi = min(n_chunks, lo + per);
    int sum = 0;
    for (int c = lo; c < hi; ++c) sum += counts[c];
    part[l] = sum;
    barrier(CLK_LOCAL_MEM_FENCE);
    if (l == 0) {
        int run = 0;
        for (int k = 0; k < LOCAL_SIZE; ++k) {
            const int t = part[k];
            part[k] = run;
            run += t;
        }
        total[0] = run;
    }
    barrier(CLK_LOCAL_MEM_FENCE);
    int run = part[l];
    for (int c = lo; c < hi; ++c) {
        offsets[c] = run;
        run += counts[c];
    }
}

// Pass 4 for corners: number the firsts in order; first[id] = the corner index.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_emit_corners(__global int *slots, __global const int *slot_of, const int n, const int chunk,
                  const int n_chunks, __global const uchar *is_first, __global const int *offsets,
                  __global long *first) {
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(n, lo + chunk);
    int id = offsets[c];
    for (int i = lo; i < hi; ++i) {
        if (is_first[i]) {
            slots[slot_of[i]] = id;
            first[id] = i;
            ++id;
        }
    }
}

// Pass 4 for sides: number the firsts in order; edge_vertices[id] = the side's (min, max) vertex ids, first_side[id]
// = last_side[id] = the side (3f + k) itself, count[id] = forward[id] = 0 (for pass 5).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_emit_sides(__global int *slots, __global const int *slot_of, const int n, const int chunk,
                const int n_chunks, __global const uchar *is_first, __global const int *offsets,
                __global const int *faces, __global int2 *edge_vertices, __global int *first_side,
                __global int *count, __global int *last_side, __global int *forward) {
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(n, lo + chunk);
    int id = offsets[c];
    for (int i = lo; i < hi; ++i) {
        if (is_first[i]) {
            slots[slot_of[i]] = id;
            edge_vertices[id] = weld_side_key(faces, i);
            first_side[id] = i;
            count[id] = 0;
            last_side[id] = i;
            forward[id] = 0;
            ++id;
        }
    }
}

// Pass 5: every item's id.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_gather_ids(__global const int *slots, __global const int *slot_of, const int n, __global int *ids) {
    const int i = get_global_id(0);
    if (i >= n) return;
    ids[i] = slots[slot_of[i]];
}

// Pass 5 for sides: every side's edge id, and the pairing the mesh check needs: how many sides each edge has
// (count), its last side (last_side; with first_side, the two facets of a manifold edge) and how many of its sides
// run from the smaller vertex id to the larger (forward: 1 of 2 when the two facets are wound consistently), all
// set by pass 4. Atomics only: the result does not depend on the order of the work-items.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_gather_sides(__global const int *slots, __global const int *slot_of, const int n,
                       __global const int *faces, __global int *ids, volatile __global int *count,
                       volatile __global int *last_side, volatile __global int *forward) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int id = slots[slot_of[i]];
    ids[i] = id;
    atomic_inc(&count[id]);
    atomic_max(&last_side[id], i);
    if (faces[i] < faces[i % 3 == 2 ? i - 2 : i + 1]) atomic_inc(&forward[id]);
}

// ---- connected components (the mesh check's shells): a lock-free union-find whose roots are the smallest nodes.
// Invariant: parent[x] <= x, and parent[x] == x for a root. Hooking sets a root's parent to a smaller root (compare
// and swap, retried when the root was hooked meanwhile); path halving lowers parent[x] to its grandparent with
// atomic_min (every value on x's path is an ancestor, and ancestors are smaller, so the minimum stays an ancestor).
// Every access to parent in weld_cc_hook is atomic; weld_cc_flatten only reads. The labels (each node's root, the
// smallest node of its component) do not depend on the order of the work-items.

// parent[x], read atomically (a compare-and-swap that never matches: parents are >= 0)
inline int weld_cc_read(volatile __global int *parent, const int x) {
    return atomic_cmpxchg(&parent[x], -1, -1);
}

inline int weld_cc_find(volatile __global int *parent, int x) {
    for (;;) {
        const int p = weld_cc_read(parent, x);
        if (p == x) return x;
        const int g = weld_cc_read(parent, p);
        if (g != p) atomic_min(&parent[x], g);
        x = g;
    }
}

__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_cc_init(__global int *parent, const int n) {
    const int i = get_global_id(0);
    if (i < n) parent[i] = i;
}

// one work-item per graph edge a[j] -- b[j]
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_cc_hook(volatile __global int *parent, __global const int *a, __global const int *b, const int m) {
    const int j = get_global_id(0);
    if (j >= m) return;
    int x = a[j], y = b[j];
    for (;;) {
        x = weld_cc_find(parent, x);
        y = weld_cc_find(parent, y);
        if (x == y) return;
        if (x < y) {
            const int t = x;
            x = y;
            y = t;
        }
        if (atomic_cmpxchg(&parent[x], x, y) == x) return;  // root x hooked under the smaller root y
    }
}

// label[i] = the root of i (after every hook)
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_cc_flatten(__global const int *parent, const int n, __global int *label) {
    const int i = get_global_id(0);
    if (i >= n) return;
    int x = i, p = parent[i];
    while (p != x) {
        x = p;
        p = parent[x];
    }
    label[i] = x;
}

#undef WELD_EMPTY
