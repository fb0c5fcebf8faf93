"""The PNG stack: one greyscale PNG per layer in a folder (``<prefix>00000.png`` upward), written atomically."""

from __future__ import annotations

import os
import re
from collections.abc import Callable, Iterable
from pathlib import Path

from ..errors import ParameterError
from ..io.atomic import atomic_path
from .coverage import Tile
from .layers import RunLayer, encode_png, run_groups
from .png import PngEncoder, encode_all
from .png_runs import png_encoders, png_group
from .spec import RasterSpec

__all__ = ["write_png_stack", "write_target"]


def write_png_stack(
    tiles: Iterable[Tile],
    spec: RasterSpec,
    directory: str | os.PathLike,
    *,
    prefix: str = "",
    digits: int = 5,
    level: int = 1,
    deflater: str = "auto",
    workers: int | None = None,
    progress: Callable[[int], None] | None = None,
    device=None,
) -> dict[str, float]:
    """Write one greyscale PNG per layer (a tile or runs, :mod:`gpuslice.raster.layers`) into ``directory``
    (``<prefix>00000.png`` upward), atomically: the directory is built under a temporary name and renamed over
    ``directory`` when complete. An existing ``directory`` is replaced only when it holds nothing but
    ``<prefix>NNNNN.png`` files (an earlier run). ``device``: the OpenCL device of the layers' runs, where their
    PNGs are made (``kernels/png.cl``) at ``level`` 1; None: numpy, in processes where the command allows them."""
    out = Path(os.fspath(directory))
    check_stack_folder(out, prefix)
    enc = PngEncoder(*spec.png_size, level, deflater)
    with atomic_path(out) as tmp:
        tmp.mkdir()

        from .png_procs import threads_for
        from .png_procs import write_group as write_procs

        device, pool = png_encoders(level, device, workers)

        def encode_and_write(pair: tuple[int, Tile]) -> bytes:  # in the pool: file creation overlaps the encoding
            k, item = pair
            data = encode_png(item, enc)
            (tmp / f"{prefix}{k:0{digits}d}.png").write_bytes(data)
            return data

        def group_and_write(pairs: list[tuple[int, Tile | RunLayer]]) -> list[bytes] | list[int]:  # on a worker thread
            pngs = png_group(device, [item for _, item in pairs], enc.nx, enc.ny)
            if pngs is not None:  # made on the device, written here
                for (k, _), data in zip(pairs, pngs, strict=True):
                    (tmp / f"{prefix}{k:0{digits}d}.png").write_bytes(data)
                return pngs
            if pool is None or not isinstance(pairs[0][1], RunLayer):
                return [encode_and_write(pair) for pair in pairs]
            paths = [tmp / f"{prefix}{k:0{digits}d}.png" for k, _ in pairs]  # written by the processes
            return write_procs(pool, [item for _, item in pairs], enc.nx, enc.ny, paths)

        stats = encode_all(enumerate(tiles), encode_and_write, lambda k, data: None, threads_for(pool, workers),
                           progress=progress, many=group_and_write,
                           chunk=lambda pairs: run_groups(pairs, key=lambda pair: pair[1]))
    return stats


def check_stack_folder(out: Path, prefix: str) -> None:
    """A :class:`ParameterError` unless the folder ``out`` may take a stack named ``prefix``: it does not exist, or
    holds nothing but an earlier stack of this name (it is replaced as a whole). The pipeline asks before slicing
    too, so that the refusal comes before the work."""
    if out.exists() and not out.is_dir():
        raise ParameterError(f"{out}: exists and is not a directory")
    if out.is_dir():
        layer = re.compile(re.escape(prefix) + r"\d+\.png")
        others = [p.name for p in out.iterdir() if not (p.is_file() and layer.fullmatch(p.name))]
        if others:
            raise ParameterError(f"{out}: directory holds other files ({others[0]}, ...); give a new or empty one")


def write_target(tiles: Iterable[Tile], target) -> dict[str, float]:
    """The registry's writer (:mod:`gpuslice.raster.outputs`): a PNG stack named after ``target.name``."""
    return write_png_stack(tiles, target.spec, target.path, prefix=target.name, level=target.options.png_level,
                           deflater=target.deflater, workers=target.workers, progress=target.progress,
                           device=target.device)
