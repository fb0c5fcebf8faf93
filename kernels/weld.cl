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
//   5. weld_gather_ids: ids[i] = slots[slot_of[i]].
// Kernel boundaries order the passes; only 32-bit atomic_cmpxchg and atomic_min (OpenCL 1.2 core) are used.

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

// Pass 1 for corners: claim or find the slot of corner i's bit-identical coordinates.
// hash_and is ANDed into the hash (0xffffffff normally; tests use a few bits to force long collision chains).
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_insert_corners(__global const uint *corners, const int n, volatile __global int *slots, const uint mask,
                    const uint hash_and, __global int *slot_of) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const uint x = corners[3 * i], y = corners[3 * i + 1], z = corners[3 * i + 2];
    uint s = weld_corner_hash(x, y, z) & hash_and & mask;
    for (;;) {
        const int v = atomic_cmpxchg(&slots[s], WELD_EMPTY, i);
        if (v == WELD_EMPTY) break;  // claimed
        // v: an item already in the slot; the slot keeps its key, though v may since have been lowered
        if (corners[3 * v] == x && corners[3 * v + 1] == y && corners[3 * v + 2] == z) {
            if (i < v) atomic_min(&slots[s], i);
            break;
        }
        s = (s + 1) & mask;
    }
    slot_of[i] = (int)s;
}

// Pass 1 for facet sides: the same with the key (min, max) of the side's two vertex ids.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_insert_sides(__global const int *faces, const int n, volatile __global int *slots, const uint mask,
                  const uint hash_and, __global int *slot_of) {
    const int i = get_global_id(0);
    if (i >= n) return;
    const int2 key = weld_side_key(faces, i);
    uint s = weld_edge_hash((uint)key.x, (uint)key.y) & hash_and & mask;
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

// Pass 4 for sides: number the firsts in order; edge_vertices[id] = the side's (min, max) vertex ids.
__kernel __attribute__((reqd_work_group_size(LOCAL_SIZE, 1, 1)))
void weld_emit_sides(__global int *slots, __global const int *slot_of, const int n, const int chunk,
                const int n_chunks, __global const uchar *is_first, __global const int *offsets,
                __global const int *faces, __global int2 *edge_vertices) {
    const int c = get_global_id(0);
    if (c >= n_chunks) return;
    const int lo = c * chunk, hi = min(n, lo + chunk);
    int id = offsets[c];
    for (int i = lo; i < hi; ++i) {
        if (is_first[i]) {
            slots[slot_of[i]] = id;
            edge_vertices[id] = weld_side_key(faces, i);
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

#undef WELD_EMPTY
