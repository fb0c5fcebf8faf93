"""One call's kernel buffers for host arrays, placed where each kind of device reads and writes them fastest: the
inputs (:func:`input_buffer`), the outputs (:class:`OutputBuffers`), and :func:`drained` for their lifetime.

On a CPU device (PoCL) both are the host arrays' own memory (``USE_HOST_PTR``): the kernels read and write the
arrays in place, and a map only waits for them. On other devices (a GPU, Oclgrind) they are the device's own
memory: inputs copied in when made (``COPY_HOST_PTR``), outputs copied into the arrays after the kernels. There,
an output buffer over its array (``USE_HOST_PTR``) would be a device copy that the driver fills from the array when
it is made (OpenCL: the array's contents are the buffer's initial contents), an upload of bytes the kernels then
overwrite, and its map copies back through the driver's staging (measured on an NVIDIA H200: docs/BENCHMARKS.md,
"On a GPU").
"""

from __future__ import annotations

import contextlib

import numpy as np

__all__ = ["input_buffer", "OutputBuffers", "drained"]


def input_buffer(device, array: np.ndarray):
    """A read-only buffer holding the contiguous ``array`` for one call's kernels: on a CPU device the array's own
    memory (``USE_HOST_PTR``: no copy into fresh pages; pyopencl holds the array with the buffer), on others (a GPU)
    a copy (``COPY_HOST_PTR``). ``array`` must not change, and the buffer must be held, until the kernels that read it
    are done (the array is freed with the buffer: on an exception, wait for the queue first, :func:`drained`)."""
    import pyopencl as cl

    share = cl.mem_flags.USE_HOST_PTR if device.is_cpu else cl.mem_flags.COPY_HOST_PTR
    return cl.Buffer(device.context, cl.mem_flags.READ_ONLY | share, hostbuf=array)


@contextlib.contextmanager
def drained(q):
    """On an exception, wait for the queue ``q`` before it propagates: buffers over host arrays (``USE_HOST_PTR``:
    the inputs on a CPU device, the outputs) must outlive the commands that use them, and unwinding frees them."""
    try:
        yield
    except BaseException:
        with contextlib.suppress(Exception):
            q.finish()
        raise


class OutputBuffers:
    """Write-only buffers for ``arrays`` (contiguous, each at least one byte's worth or empty) on ``device``:
    :attr:`buffers` go to the kernels; :meth:`fetch` returns the arrays as the kernels left them (read and written
    by the host until :meth:`release`). The arrays and this object must be held until then (on an exception, wait
    for the queue first: :func:`drained`)."""

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
