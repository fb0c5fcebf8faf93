"""Which OpenCL device is used by default: a PoCL whose LLVM does not know the host CPU is passed over."""

from __future__ import annotations

import pytest

from gpuslice import device as devmod
from gpuslice.device import DeviceError, cpu_unknown_to_pocl, list_devices, resolve

POCL = "Portable Computing Language"


def _entry(i: int, platform: str, kind: str, version: str) -> dict:
    return {"id": f"{i}:0", "platform": platform, "device": f"dev{i}", "type": kind, "version": version,
            "platform_version": "", "compute_units": 2, "global_mem_mib": 1024, "driver": ""}


GENERIC = _entry(0, POCL, "ALL | CPU", "OpenCL 3.0 PoCL HSTR: pthread-x86_64-unknown-linux-gnu-generic")
KNOWN = _entry(1, POCL, "ALL | CPU", "OpenCL 3.0 PoCL HSTR: pthread-x86_64-pc-linux-gnu-skylake-avx512")
OTHER = _entry(2, "Intel(R) OpenCL", "CPU", "OpenCL 3.0 (Build 0)")
GPU = _entry(3, "NVIDIA CUDA", "GPU", "OpenCL 3.0 CUDA")


@pytest.mark.parametrize(
    ("devices", "chosen"),
    [
        ([GENERIC, KNOWN], "1:0"),  # the PoCL that cannot build for this CPU is passed over
        ([KNOWN, GENERIC], "1:0"),
        ([OTHER, GENERIC, KNOWN], "1:0"),
        ([GENERIC, OTHER], "0:0"),  # nothing better: the error comes at the build, with its hint
        ([GENERIC, KNOWN, GPU], "3:0"),
    ],
)
def test_the_default_passes_over_a_pocl_that_does_not_know_the_cpu(monkeypatch, devices, chosen):
    monkeypatch.delenv(devmod.ENV_VAR, raising=False)
    monkeypatch.setattr(devmod, "list_devices", lambda: devices)
    assert resolve(None)["id"] == chosen
    assert cpu_unknown_to_pocl(GENERIC) and not cpu_unknown_to_pocl(KNOWN) and not cpu_unknown_to_pocl(OTHER)


def test_a_named_device_is_taken_even_when_it_cannot_build(monkeypatch):
    monkeypatch.setattr(devmod, "list_devices", lambda: [KNOWN, GENERIC])
    assert resolve("0")["id"] == "0:0"  # the PoCL that cannot build, named by its index
    with pytest.raises(DeviceError, match="not found"):
        resolve("9:0")


def test_the_default_device_of_this_machine_builds_the_kernels():
    """On this machine (whatever its CPU), the default device is one whose PoCL can build for it."""
    devices = list_devices()
    if not devices:
        pytest.skip("no OpenCL device")
    chosen = resolve(None)
    usable = [d for d in devices if not cpu_unknown_to_pocl(d)]
    if usable:
        assert not cpu_unknown_to_pocl(chosen)
    pocl = [d for d in devices if "portable computing language" in d["platform"].lower()]
    if pocl:  # the documented name piece finds a PoCL device (its platform is called "Portable Computing Language")
        assert resolve("pocl") in pocl


def test_devices_command_marks_the_pocl_that_cannot_build(monkeypatch, capsys):
    from gpuslice.cli import main

    monkeypatch.delenv(devmod.ENV_VAR, raising=False)
    monkeypatch.setattr(devmod, "list_devices", lambda: [GENERIC, KNOWN])
    assert main(["devices"]) == 0
    lines = capsys.readouterr().out.splitlines()
    generic = next(x for x in lines if "dev0" in x)
    known = next(x for x in lines if "dev1" in x)
    assert "cannot build for this CPU" in generic and not generic.startswith("*")
    assert "cannot build" not in known and known.startswith("*")


def test_a_name_picks_the_device_of_that_name_that_can_build(monkeypatch):
    monkeypatch.setattr(devmod, "list_devices", lambda: [GENERIC, KNOWN, OTHER])
    assert resolve("pocl")["id"] == "1:0"
    assert resolve("dev0")["id"] == "0:0"  # named alone: taken (its build error then says why)
    assert resolve("intel")["id"] == "2:0"
