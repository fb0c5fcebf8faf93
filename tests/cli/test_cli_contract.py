"""The command line's contract: every command and option that existed before the one-pipeline redesign is still
there (help texts may change), and every command's options come from the option dataclasses with their defaults."""

from __future__ import annotations

import click
import pytest

from gpuslice import Placement, SliceParams
from gpuslice.cli import cli
from gpuslice.options import options_of

# the commands and their options (and arguments) as of 8c0d960, the commit before the redesign
KEPT = {
    "batch": {
        "--adaptive",
        "--backend",
        "--device",
        "--fill-rule",
        "--first-layer",
        "--fit",
        "--force",
        "--format",
        "--glob",
        "--max-area",
        "--max-cusp",
        "--max-gap",
        "--max-height",
        "--min-height",
        "--output",
        "--quiet",
        "--raster",
        "--raster-opt",
        "--report",
        "--roi-ladder",
        "--roi-quantile",
        "--roi-threshold",
        "--roi-windows",
        "--scale",
        "--scheduler",
        "--smooth",
        "--thickness",
        "--threads",
        "--transfer",
        "--workers",
        "--z-mode",
        "-j",
        "-o",
        "-q",
        "-t",
        "ARG:inputs",
        "inputs",
    },
    "bench": {
        "--adaptive",
        "--backend",
        "--csv",
        "--device",
        "--fit",
        "--json",
        "--max-area",
        "--max-cusp",
        "--max-height",
        "--min-height",
        "--no-quality",
        "--plots",
        "--ref-thickness",
        "--repeat",
        "--roi-ladder",
        "--roi-quantile",
        "--roi-threshold",
        "--roi-windows",
        "--scale",
        "--smooth",
        "--thickness",
        "-t",
        "ARG:model",
        "model",
    },
    "devices": {"--device", "--json"},
    "info": {"--fit", "--json", "--scale", "ARG:model", "model"},
    "plot": {
        "--adaptive",
        "--backend",
        "--device",
        "--fit",
        "--layers",
        "--max-area",
        "--max-cusp",
        "--max-height",
        "--min-height",
        "--out",
        "--roi-ladder",
        "--roi-quantile",
        "--roi-threshold",
        "--roi-windows",
        "--scale",
        "--smooth",
        "--thickness",
        "-o",
        "-t",
        "ARG:model",
        "model",
    },
    "raster": {
        "--backend",
        "--device",
        "--exposure",
        "--exposure-first",
        "--fill-rule",
        "--first-layer",
        "--fit",
        "--gamma",
        "--job-name",
        "--keep-xy",
        "--landscape",
        "--max-gap",
        "--mirror-x",
        "--mirror-y",
        "--no-mirror-x",
        "--no-mirror-y",
        "--no-progress",
        "--output",
        "--pixel",
        "--pixel-y",
        "--png-level",
        "--portrait",
        "--printer",
        "--progress",
        "--quiet",
        "--raster-backend",
        "--report",
        "--resolution",
        "--scale",
        "--supersample",
        "--thickness",
        "--workers",
        "--z-mode",
        "-o",
        "-q",
        "-t",
        "ARG:model",
        "model",
    },
    "shape": {"--output", "-o", "ARG:name", "name"},
    "slice": {
        "--adaptive",
        "--backend",
        "--device",
        "--fill-rule",
        "--first-layer",
        "--fit",
        "--max-area",
        "--max-cusp",
        "--max-gap",
        "--max-height",
        "--min-height",
        "--output",
        "--quiet",
        "--report",
        "--roi-ladder",
        "--roi-quantile",
        "--roi-threshold",
        "--roi-windows",
        "--scale",
        "--smooth",
        "--thickness",
        "--z-mode",
        "-o",
        "-q",
        "-t",
        "ARG:model",
        "model",
    },
    "view": {
        "--backend",
        "--device",
        "--fill-rule",
        "--first-layer",
        "--fit",
        "--mask-every",
        "--max-gap",
        "--output",
        "--printer",
        "--quiet",
        "--raster",
        "--scale",
        "--thickness",
        "--title",
        "--z-mode",
        "-o",
        "-q",
        "-t",
        "ARG:source",
        "source",
    },
}


def _params(name: str) -> dict[str, click.Parameter]:
    cmd = cli.get_command(click.Context(cli), name)
    assert cmd is not None, name
    out = {}
    for p in cmd.params:
        for o in (*p.opts, *getattr(p, "secondary_opts", [])):
            out[o] = p
        if isinstance(p, click.Argument):
            out["ARG:" + p.name] = p
    return out


@pytest.mark.parametrize("name", sorted(KEPT))
def test_every_command_and_option_kept(name):
    missing = KEPT[name] - set(_params(name))
    assert not missing, f"gpuslice {name} lost {sorted(missing)}"


@pytest.mark.parametrize("name", ["slice", "raster", "view", "batch"])
def test_slicing_options_come_from_the_dataclasses(name):
    """Each slicing command takes every SliceParams and Placement option, with the dataclass's choices and (where
    the command shows defaults) its default; raster's thickness is its own (0.05 mm)."""
    params = _params(name)
    for info in [*options_of(SliceParams), *options_of(Placement)]:
        if not info.flags:
            continue
        p = params[info.flag]
        if info.choices is not None:
            assert list(p.type.choices) == [str(c) for c in info.choices]
        if name in ("slice", "batch") and info.parse is None and info.type is not bool:
            assert p.default == info.default, (name, info.name)
    assert params["--thickness"].default == {"raster": 0.05, "view": None}.get(name, 0.1)


@pytest.mark.parametrize("name", ["raster", "check"])
def test_preset_options_say_the_preset_comes_first(name):
    """The display and print options a ``--printer`` preset sets are None unless given (the preset's value, else the
    dataclass's default, applies): their help names both, so ``--help`` does not promise 15 s where a preset gives
    its own bottom exposure."""
    from gpuslice.raster.settings import PrintSettings
    from gpuslice.raster.spec import RasterSpec

    params = _params(name)
    classes = (RasterSpec, PrintSettings) if name == "raster" else (PrintSettings,)
    for cls in classes:
        for info in options_of(cls):
            if not info.flags or info.type is bool and not info.negatable:
                continue
            p = params[info.flag.split("/")[0]]
            assert p.default is None, (name, info.name)
            assert "--printer preset's" in p.help, (name, info.name, p.help)
    assert "[default: 15.0, or the --printer preset's]" in params["--bottom-exposure"].help
