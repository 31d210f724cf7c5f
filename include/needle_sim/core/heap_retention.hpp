#pragma once
// glibc hands large freed blocks back to the kernel (blocks above the mmap threshold, and
// the top of the heap above the trim threshold), and the next allocation of that size
// page-faults its memory in again, zero-filled. A simulation frees and reallocates the same
// few megabytes at every mesh change and factorisation: on the 2-core VM a fault cost about
// as much as filling the page, and the adaptive DBS pre-step spent 5-8 % of its time there
// (doc/benchmarks.md, "Static solves"). Programs that step in real time (the tool, the ROS
// node) keep freed memory for reuse instead: the process holds its peak heap, as real-time
// practice asks. Process-wide: a nodelet does not call it (the manager is not ours).
#include <malloc.h>

namespace needle_sim {

inline void retainFreedHeap() {
  // Blocks up to 64 MiB come from the heap (above, e.g. a fine mesh's factor, mmap as
  // before), and the heap keeps up to 512 MiB of free memory at its top.
  mallopt(M_MMAP_THRESHOLD, 64 << 20);
  mallopt(M_TRIM_THRESHOLD, 512 << 20);
}

}  // namespace needle_sim
