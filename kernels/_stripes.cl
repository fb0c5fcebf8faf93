// Counters split by stripes of work-groups (walk.cl, segment_edges.cl): every kernels/*.cl file is built into one
// program, in file-name order, so this file serves them all.
//
// Where work-items of neighbouring segments (neighbouring facets, so the same layers) count into one counter per
// layer, the cores that run neighbouring work-groups fight over that counter's cache line: on PoCL one such counter
// a layer cost 4x the rest of chaining's linking. Each counter is therefore kept STRIPES times (the build option,
// gpuslice.device.STRIPES), item i counting in stripe stripe_of(i): work-groups that run at the same time count on
// different counters, and the stripes' counts are summed (or prefix-summed) afterwards.

inline int stripe_of(const int i) { return (i / LOCAL_SIZE) % STRIPES; }
