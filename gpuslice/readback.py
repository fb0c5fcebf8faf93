"""Output buffers: what a call's kernels write and the host then reads, placed where each kind of device reads
back fastest.

On a CPU device (PoCL) the buffers are the host arrays' own memory (``USE_HOST_PTR``): the kernels write the
arrays in place, and a map only waits for them. On other devices (a GPU, Oclgrind) they are the device's own
memory, copied into the arrays after the kernels: there, a ``USE_HOST_PTR`` buffer is a device copy that the
driver fills from the array when it is made (OpenCL: the array's contents are the buffer's initial contents), an
upload of bytes the kernels then overwrite, and its map copies back through the driver's staging (measured on an
NVIDIA H200: docs/BENCHMARKS.md, "On a GPU").
"""

from __future__ import annotations

import numpy as np

__all__ = ["OutputBuffers"]


class OutputBuffers:
    """Write-only buffers for ``arrays`` (contiguous, each at least one byte's worth or empty) on ``device``:
    :attr:`buffers` go to the kernels; :meth:`fetch` returns the arrays as the kernels left them (read and written
    by the host until :meth:`release`). The arrays and this object must be held until then (on an exception, wait
    for the queue first: :func:`gpuslice.device.drained`)."""

    IN_PLACE: bool | None = None  #: None: in the arrays on a CPU device only (tests: False, the copies on any)

    def __init__(self, device, arrays: list[np.ndarray]) -> None:
        import pyopencl as cl

        self.arrays = arrays
        self._in_place = bool(device.is_cpu) if self.IN_PLACE is None else self.IN_PLACE
        mf = cl.mem_flags
        if self._in_place:
            self.buffers = [cl.Buffer(device.context, mf.WRITE_ONLY | mf.USE_HOST_PTR, hostbuf=a) for a in arrays]
        else:
            self.buffers = [cl.Buffer(device.context, mf.WRITE_ONLY, max(a.nbytes, 4)) for a in arrays]
        self._maps: list[np.ndarray] = []

    def fetch(self, q) -> list[np.ndarray]:
        """The arrays once the commands enqueued on ``q`` before this call are done (one wait)."""
        import pyopencl as cl

        if self._in_place:
            flags = cl.map_flags.READ | cl.map_flags.WRITE
            self._maps = [cl.enqueue_map_buffer(q, b, flags, 0, a.shape, a.dtype, is_blocking=False)[0]
                          for a, b in zip(self.arrays, self.buffers, strict=True)]
            q.finish()
            return self._maps
        events = []  # (held until the queue is finished: a dropped event waits holding the GIL, device.TRANSFERS)
        for a, b in zip(self.arrays, self.buffers, strict=True):
            if a.nbytes:
                event = cl.enqueue_copy(q, a, b, is_blocking=False)
                events.append(event)
        q.finish()
        return list(self.arrays)

    def release(self, q) -> None:
        """Hand the mapped arrays back to the device (a CPU device's maps; nothing elsewhere)."""
        for m in self._maps:
            m.base.release(q)
        self._maps = []
