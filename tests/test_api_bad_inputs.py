"""The public Python API against bad input, as a user of a geometry library meets it: one-line errors of the
project's own classes (:class:`~gpuslice.errors.GpusliceError`) naming the argument, raised at the entry point, never
a numpy/shapely error from deep inside nor a silently wrong result (a truncated layer index, a misread flag, an
ignored argument). The command line's own sweep is ``tests/cli/test_bad_inputs_sweep.py``. Every case here failed
before its fix."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import gpuslice
from gpuslice import Placement, SliceParams, SliceResult, formats
from gpuslice.checks import CheckOptions, run_checks
from gpuslice.errors import InvalidGeometryError, MeshFileError, ParameterError
from gpuslice.raster import PrintSettings, RasterSpec, masks
from gpuslice.slicing.result import LayerIndexError

V = np.array([[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0],
              [0, 0, 10], [10, 0, 10], [10, 10, 10], [0, 10, 10]], float)
F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
              [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]])
TRI = V[F]
SPEC = RasterSpec(resolution=(300, 300), pixel=0.05)


@pytest.fixture(scope="module")
def cube():
    return gpuslice.mesh_from_arrays(V, F)


@pytest.fixture(scope="module")
def res(cube):
    return gpuslice.slice_mesh(cube, thickness=2.5, backend="numpy")  # 4 layers of a 10 mm cube


def _one_line(exc: pytest.ExceptionInfo, *words: str) -> None:
    text = str(exc.value)
    assert "\n" not in text and all(w in text for w in words), text


# ---- meshes ----------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("tri, words", [
    (np.full((2, 3, 3), "a"), ["triangles must be real numbers", "<U1"]),          # was numpy's ValueError
    (np.full((2, 3, 3), "a", dtype=object), ["triangles must be a numeric array"]),
    ([[[0, 0, 0], [1, 0, 0]], [[0, 0, 0]]], ["triangles must be a numeric array"]),  # ragged: was ValueError
    (TRI.astype(complex), ["triangles must be real numbers", "complex"]),          # was sliced, imaginary dropped
    (TRI.astype(bool), ["triangles must be real numbers", "bool"]),                # was sliced as 0/1 corners
])
def test_triangles_of_no_real_numbers_are_refused(tri, words):
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no ComplexWarning on the way to the error
        with pytest.raises(ParameterError) as exc:
            gpuslice.mesh_from_triangles(tri)
    _one_line(exc, "<triangles>", *words)


def test_triangles_as_python_objects_still_load():
    """Lists, object arrays of numbers and anything with ``__array__`` are real numbers too."""
    class Tensor:
        def __array__(self, dtype=None, copy=None):
            return TRI

    for tri in (TRI.tolist(), TRI.astype(object), Tensor(), np.asfortranarray(TRI)):
        np.testing.assert_array_equal(gpuslice.mesh_from_triangles(tri).triangles,
                                      gpuslice.mesh_from_triangles(TRI).triangles)


@pytest.mark.parametrize("normals", [np.zeros((5, 3)), np.zeros((12, 2)), "x"])
def test_normals_of_the_wrong_shape_are_refused(normals):
    """Five normals for twelve facets were stored as they were: ``Mesh.info()`` then failed far from the cause."""
    with pytest.raises(ParameterError) as exc:
        gpuslice.mesh_from_triangles(TRI, normals=normals)
    _one_line(exc, "<triangles>", "normals")


@pytest.mark.parametrize("kw, param", [
    ({"scale": "2"}, "scale"), ({"scale": [2]}, "scale"), ({"scale": np.array([1.0, 2.0])}, "scale"),
    ({"scale": True}, "scale"), ({"fit": "80"}, "fit"), ({"fit": [80]}, "fit"),
])
def test_scale_and_fit_must_be_numbers(kw, param):
    """Were numpy TypeErrors (``isfinite`` of a string), or ``scale=True`` taken as 1."""
    for call in (lambda: gpuslice.mesh_from_triangles(TRI, **kw), lambda: gpuslice.load_mesh((V, F), **kw),
                 lambda: gpuslice.slice_mesh((V, F), backend="numpy", **kw)):
        with pytest.raises(ParameterError) as exc:
            call()
        assert exc.value.params == (param,)
        _one_line(exc, f"{param} must be a positive")


@pytest.mark.parametrize("kw", [{"scale": -1}, {"scale": 0}, {"scale": float("nan")}, {"scale": "2"},
                                {"fit": -5}, {"fit": float("inf")}, {"fit": [80]}, {"scale": True}])
def test_placement_is_checked_when_made(kw):
    """``Placement(scale=-1)`` was accepted and failed only once a mesh was loaded with it."""
    with pytest.raises(ParameterError) as exc:
        Placement(**kw)
    assert exc.value.params == tuple(kw)
    assert Placement(scale=np.float32(2.0)).scale == 2.0 and Placement(fit=np.int64(80)).fit == 80


def test_a_scale_that_collapses_the_mesh_is_refused():
    """scale=1e-50 rounded every coordinate to 0: a mesh of no extent and an empty slicing, silently."""
    with pytest.raises(InvalidGeometryError) as exc:
        gpuslice.mesh_from_triangles(TRI, scale=1e-50)
    _one_line(exc, "<triangles>", "float32's smallest length")
    assert gpuslice.mesh_from_triangles(TRI, scale=1e-30).height > 0  # small, not collapsed


@pytest.mark.parametrize("faces, words", [
    (F.astype(float), ["faces must be integer vertex indices", "float64"]),   # was IndexError
    (F + 0.5, ["faces must be integer vertex indices"]),
    (F.astype(bool), ["faces must be integer vertex indices", "bool"]),      # was IndexError (a boolean mask)
    (F.astype(object), ["faces must be integer vertex indices", "object"]),
])
def test_mesh_from_arrays_checks_faces_as_load_mesh_does(faces, words):
    with pytest.raises(ParameterError) as exc:
        gpuslice.mesh_from_arrays(V, faces)
    _one_line(exc, "<arrays>", *words)


@pytest.mark.parametrize("source", [lambda: gpuslice.mesh_from_arrays(V.astype(complex), F),
                                    lambda: gpuslice.load_mesh((V.astype(complex), F)),
                                    lambda: gpuslice.mesh_from_arrays(np.full((8, 3), "a"), F)])
def test_vertices_of_no_real_numbers_are_refused(source):
    """Complex vertices were sliced with a ComplexWarning, their imaginary part dropped; strings were ValueErrors."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ParameterError) as exc:
            source()
    _one_line(exc, "<arrays>", "vertices must be real numbers")


def test_mesh_from_arrays_is_the_same_mesh_as_before():
    a, b = gpuslice.mesh_from_arrays(V, F), gpuslice.mesh_from_triangles(V[F], name="<arrays>")
    for name in ("vertices", "faces", "face_edges", "edge_vertices"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_load_mesh_name_and_path_errors(tmp_path):
    with pytest.raises(ParameterError) as exc:  # was a TypeError from os.path
        gpuslice.load_mesh(b"solid x\nendsolid x\n", name=5)
    _one_line(exc, "name must be a string")
    with pytest.raises(MeshFileError) as exc:  # was ValueError: embedded null byte
        gpuslice.load_mesh(str(tmp_path / "a\0b.stl"))
    _one_line(exc, "NUL")


# ---- slicing ---------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("kw, words", [
    ({"z": "abc"}, ["z values must be numbers"]),                                     # was ValueError
    ({"z": np.array([[1.0, 2.0], [3.0, 4.0]])}, ["z values must be one number per layer", "(2, 2)"]),  # was flattened
    ({"z": np.array([1 + 1j, 2])}, ["z values must be numbers", "complex"]),          # was sliced at z = 1, 2
    ({"z": np.array([False, True])}, ["z values must be numbers", "bool"]),           # was sliced at z = 0, 1
    ({"z": [1, 2, 3], "layer_thickness": [1, 2]}, ["one number or one per z value (3)", "got 2"]),  # numpy's
    ({"z": [1, 2, 3], "layer_thickness": [[1], [1], [1]]}, ["thicknesses must be one number per layer"]),
    ({"z": [1, 2, 3], "layer_thickness": "a"}, ["thicknesses must be numbers"]),
])
def test_bad_z_planes_and_thicknesses(cube, kw, words):
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ParameterError) as exc:
            gpuslice.slice_mesh(cube, backend="numpy", **kw)
    _one_line(exc, "schedule:", *words)


def test_layer_thickness_without_z_is_refused(cube):
    """It was ignored: 0.1 mm layers (the default) came out where 0.5 mm ones were meant."""
    with pytest.raises(ParameterError) as exc:
        gpuslice.slice_mesh(cube, layer_thickness=0.5, backend="numpy")
    _one_line(exc, "layer_thickness goes with explicit z", "thickness=")
    with pytest.raises(ParameterError):
        gpuslice.slice_mesh(cube, schedule=gpuslice.from_z([1.0]), layer_thickness=0.5, backend="numpy")
    r = gpuslice.slice_mesh(cube, z=[1.0, 2.0], layer_thickness=0.5, backend="numpy")
    assert r.thickness.tolist() == [0.5, 0.5]


@pytest.mark.parametrize("call, words", [
    (lambda m: gpuslice.slice_mesh(m, bogus=1), ["unknown slicing option 'bogus'"]),   # SliceParams.__init__()'s
    (lambda m: gpuslice.slice_mesh(m, {"thickness": 1}), ["params must be a SliceParams", "dict"]),  # asdict()'s
    (lambda m: gpuslice.slice_mesh(m, 5), ["params must be a SliceParams", "int"]),
    (lambda m: gpuslice.slice_mesh(m, schedule=[1, 2, 3]), ["schedule must be a Schedule", "list"]),  # 'no .z'
])
def test_slice_mesh_arguments_of_the_wrong_kind(cube, call, words):
    with pytest.raises(ParameterError) as exc:
        call(cube)
    _one_line(exc, *words)


@pytest.mark.parametrize("kw, param", [
    ({"thickness": "0.1"}, "thickness"), ({"thickness": True}, "thickness"), ({"thickness": (0.1, 0.2)}, "thickness"),
    ({"thickness": None}, "thickness"), ({"first_layer": "a"}, "first_layer"), ({"max_gap": "2"}, "max_gap"),
    ({"max_gap": None}, "max_gap"), ({"max_segments_per_batch": "1"}, "max_segments_per_batch"),
    ({"max_segments_per_batch": 1.5}, "max_segments_per_batch"),
    ({"max_segments_per_batch": float("nan")}, "max_segments_per_batch"), ({"max_cusp": "a"}, "max_cusp"),
    ({"smooth": "a"}, "smooth"), ({"roi_quantile": "a"}, "roi_quantile"), ({"roi_windows": 1.5}, "roi_windows"),
    ({"roi_ladder": "1,0.5"}, "roi_ladder"), ({"roi_ladder": 1.0}, "roi_ladder"),
    ({"roi_ladder": (1, "a")}, "roi_ladder"),
    ({"roi_threshold": "5"}, "roi_threshold"), ({"z_mode": 5}, "z_mode"), ({"device": 5}, "device"),
])
def test_slice_params_of_the_wrong_type(kw, param):
    """Each was accepted (then a TypeError deep in a stage, or a bool read as 1 mm) or a bare TypeError."""
    with pytest.raises(ParameterError) as exc:
        SliceParams(**kw)
    assert exc.value.params == (param,)
    _one_line(exc, param)


def test_slice_params_keep_valid_values():
    p = SliceParams(thickness=np.float32(0.5), max_segments_per_batch=2e6, roi_ladder=[1.0, 0.5], roi_threshold=5)
    assert p.roi_ladder == (1.0, 0.5) and hash(p)  # a list becomes the tuple a frozen dataclass can hash
    assert p.thickness == 0.5 and type(p.thickness) is float


def test_numpy_numbers_as_options_can_be_saved(cube, tmp_path):
    """np.float32/np.int64 options went into the report as they were: ``save()`` then failed in ``json.dumps``."""
    # (as SliceParams: roi options given as keywords to uniform layers are refused, as they would be ignored)
    r = gpuslice.slice_mesh(cube, SliceParams(thickness=np.float32(2.5), roi_windows=np.int64(2),
                                              roi_ladder=(np.float32(1),), backend="numpy"))
    r.save(tmp_path / "r.npz")
    assert SliceResult.load(tmp_path / "r.npz").meta["params"]["thickness"] == 2.5
    np.testing.assert_array_equal(r.z, gpuslice.slice_mesh(cube, thickness=2.5, backend="numpy").z)


@pytest.mark.parametrize("call", [
    lambda: gpuslice.uniform(10, "a"), lambda: gpuslice.uniform("a", 0.1), lambda: gpuslice.uniform(10, [0.1]),
    lambda: gpuslice.uniform(10, np.array([0.1, 0.2])), lambda: gpuslice.uniform(10, 0.1, first_layer="a"),
    lambda: gpuslice.uniform(10, True), lambda: gpuslice.from_z("abc"), lambda: gpuslice.from_z([[1, 2], [3, 4]]),
    lambda: gpuslice.from_z([1, 2, 3], [1, 2]), lambda: gpuslice.Schedule("ab", "cd"),
])
def test_schedules_of_the_wrong_type(call):
    with pytest.raises(ParameterError) as exc:
        call()
    _one_line(exc)


# ---- the result ------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("i", [1.5, "1", None, True])
def test_layer_index_must_be_an_integer(res, i):
    """1.5 was an IndexError from numpy, '1' and None TypeErrors, True layer 1."""
    with pytest.raises(ParameterError) as exc:
        res.layer(i)
    _one_line(exc, "layer index must be an integer")
    assert res.layer(np.int64(2)).index == 2 and res.layer(-1).index == 3


def test_index_out_of_range_is_both_ours_and_an_index_error(res):
    for call in (lambda: res.layer(4), lambda: res.layer(-5), lambda: res.layer(0).loop(5)):
        with pytest.raises(LayerIndexError) as exc:
            call()
        assert isinstance(exc.value, IndexError) and isinstance(exc.value, ParameterError)
        _one_line(exc, "out of range")


@pytest.mark.parametrize("layers", ["a", 1.5, [100]])
def test_plot_layers_are_checked(res, layers):
    pytest.importorskip("matplotlib")
    with pytest.raises(ParameterError) as exc:  # were ValueError from int('a'), a silent int(1.5), a bare IndexError
        res.plot(layers=layers)
    _one_line(exc, "layer")


def _saved(res, tmp_path, **change) -> str:
    path = tmp_path / "ok.npz"
    res.save(path)
    with np.load(path) as data:
        arrays = dict(data)
    for key, value in change.items():
        if callable(value):
            for k in [k for k in arrays if k.startswith(key)]:
                arrays[k] = value(arrays[k])
        else:
            arrays[key] = value
    bad = tmp_path / "bad.npz"
    np.savez(bad, **arrays)
    return str(bad)


@pytest.mark.parametrize("change, words", [
    ({"points": np.zeros((5, 3), np.float32)}, ["points must be (P, 2) float32"]),      # was shapely's ValueError
    ({"points": np.array([["a", "b"]])}, ["points must be (P, 2) float32"]),             # was ValueError
    ({"points": lambda p: p.astype(np.float64)}, ["points must be (P, 2) float32", "float64"]),  # kept float64
    ({"z": lambda z: z[::-1].copy()}, ["z must be strictly increasing"]),                 # silently loaded
    ({"loop_layer": lambda la: la[::-1].copy()}, ["loop_layer disagrees with layer_offsets"]),  # polygons moved
    ({"loop_offsets": lambda o: o * 100}, ["loop_offsets must rise from 0 to"]),           # shapely's ValueError
    ({"layer_offsets": lambda o: o[:2]}, ["layer_offsets holds 2 values, expected 5"]),    # IndexError
    ({"z": lambda z: z[:2]}, ["layer_offsets holds 5 values, expected 3"]),                # silently 2 layers
    ({"loop_offsets": lambda o: o.astype(float)}, ["loop_offsets must be 1-D"]),           # numpy's TypeError
    ({"loop_parent": lambda p: p + 1000}, ["loop_parent out of range"]),                  # silently loaded
    ({"area": lambda a: np.full_like(a, np.nan)}, ["not finite"]),                         # NaN areas
    ({"repairs__": lambda r: r[:1]}, ["repairs__", "must be 4 integers"]),                # silently loaded
    ({"meta_json": np.frombuffer(b"[1,2]", np.uint8)}, ["meta_json must hold an object"]),
    ({"z": np.float64(1.0)}, ["z must be 1-D"]),                                          # IndexError
    # values no slice makes (a helper's fuzzing with warnings as errors): each ended in a numpy warning, an internal
    # error or a silently wrong page or mask (the display fit check overflowed) in view, view --raster or --check
    ({"points": lambda p: np.where(p == p.max(), np.float32(np.inf), p)}, ["points must be finite"]),
    ({"points": lambda p: np.where(p == p.max(), np.float32(3.4e38), p)}, ["within 1e18 mm"]),
    ({"points": lambda p: np.where(p == p.max(), np.frombuffer(b"\x00\x00\xa0\x7f", np.float32)[0], p)},
     ["points must be finite"]),                                                          # a signalling NaN
    ({"thickness": lambda t: np.full_like(t, 1e308)}, ["thickness must be more than 0"]),  # cumsum overflowed
    ({"thickness": lambda t: -t}, ["thickness must be more than 0"]),
    ({"z": lambda z: z * 1e300}, ["z must lie within 1e18 mm"]),
    ({"area": lambda a: np.full_like(a, 1e308)}, ["area beyond"]),                        # resin volume overflowed
    ({"loop_offsets": lambda o: o.astype(np.uint64) + np.uint64(2**63)}, ["loop_offsets holds values beyond int64"]),
    ({"meta_json": np.frombuffer(b'{"facets": 1e999}', np.uint8)}, ["facets must be a whole number"]),  # inf
    ({"meta_json": np.frombuffer(b'{"facets": "12"}', np.uint8)}, ["facets must be a whole number"]),
    ({"meta_json": np.frombuffer(b'{"scale": NaN}', np.uint8)}, ["scale must be a positive number"]),
    ({"meta_json": np.frombuffer(b'{"params": []}', np.uint8)}, ["params must be an object"]),    # AttributeError
    ({"meta_json": np.frombuffer(b'{"params": {"fill_rule": "x"}}', np.uint8)}, ["fill rule must be"]),
    ({"meta_json": np.frombuffer(b'{"repairs": {"filled_holes": -1}}', np.uint8)}, ["repairs must be counts"]),
    ({"meta_json": np.frombuffer(b'{"file": 3}', np.uint8)}, ["file must be text"]),
])
def test_loading_a_corrupted_result_names_the_file(res, tmp_path, change, words):
    path = _saved(res, tmp_path, **change)
    with pytest.raises(MeshFileError) as exc:
        SliceResult.load(path)
    _one_line(exc, path, "not a gpuslice result", *words)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint32, np.uint64, np.int32])
def test_a_result_saved_with_other_integer_widths_loads_as_the_slicer_makes_it(res, tmp_path, dtype):
    """Offsets and indices of any integer width whose values fit load as int64 offsets and int32 indices (uint64
    offsets were a TypeError in the layer check; uint8 ones an IndexError when rasterised)."""
    names = ["loop_offsets", "layer_offsets", "loop_layer"] + (["loop_parent"] if np.iinfo(dtype).min < 0 else [])
    assert res.n_loops and int(res.loop_offsets[-1]) <= np.iinfo(dtype).max  # (the 4-layer cube's fit any width)
    back = SliceResult.load(_saved(res, tmp_path, **{k: (lambda a: a.astype(dtype)) for k in names}))
    assert back.loop_offsets.dtype == np.int64 and back.layer_offsets.dtype == np.int64
    assert back.loop_layer.dtype == np.int32 and back.loop_parent.dtype == np.int32
    for k in ("loop_offsets", "layer_offsets", "loop_layer", "loop_parent"):
        np.testing.assert_array_equal(getattr(back, k), getattr(res, k))
    assert [p.area for p in back.to_shapely()] == [p.area for p in res.to_shapely()]


def test_a_saved_result_given_to_a_mesh_command_says_what_it_is(res, tmp_path):
    """`check part.npz` said the file looked like a ZIP archive and to name it .3mf."""
    from gpuslice.io.meshfile import read_mesh_file

    path = tmp_path / "part.npz"
    res.save(path)
    with pytest.raises(MeshFileError) as exc:
        read_mesh_file(path)
    _one_line(exc, "part.npz", "a saved slice result (.npz), not a mesh", "gpuslice view")


def test_loading_what_is_no_npz_names_the_file(res, tmp_path):
    """A .npy file (TypeError: no context manager), an empty file (EOFError), a truncated one (BadZipFile)."""
    np.save(tmp_path / "plain.npy", np.arange(3))
    (tmp_path / "empty.npz").write_bytes(b"")
    res.save(tmp_path / "ok.npz")
    (tmp_path / "cut.npz").write_bytes((tmp_path / "ok.npz").read_bytes()[:1000])
    (tmp_path / "json.npz").write_text('{"a": 1}')  # (numpy's advice was to load it with allow_pickle)
    for name in ("plain.npy", "empty.npz", "cut.npz", "json.npz"):
        with pytest.raises(MeshFileError) as exc:
            SliceResult.load(tmp_path / name)
        _one_line(exc, name, "not a gpuslice result")
        assert "pickle" not in str(exc.value)
    with pytest.raises(ParameterError):
        SliceResult.load(None)
    back = SliceResult.load(tmp_path / "ok.npz")  # a good one still loads, every array equal
    for name in ("points", "loop_offsets", "layer_offsets", "loop_parent", "z", "area"):
        np.testing.assert_array_equal(getattr(back, name), getattr(res, name))


# ---- raster, checks, formats, print settings -------------------------------------------------------------------------
@pytest.mark.parametrize("kw, words", [
    ({"layers": [1.5]}, ["layers must be a sequence of whole layer indices"]),               # was layer 1, silently
    ({"layers": np.array([True, False, True, False])}, ["whole layer indices"]),             # was layers 1, 0, 1, 0
    ({"layers": 2}, ["whole layer indices"]),                                                # TypeError: len()
    ({"layers": ["a"]}, ["whole layer indices"]),
    ({"layers": [[0, 1]]}, ["whole layer indices"]),
    ({"bounds": (0, 0, 1)}, ["bounds must be four finite numbers"]),                         # ValueError: unpack
    ({"bounds": (np.nan, 0, 1, 1)}, ["bounds must be four finite numbers"]),                 # garbage, warnings
    ({"layers": [0, -1]}, ["layer index -1 out of range 0..3", "no negative"]),              # named no value
    ({"layers": [7]}, ["layer index 7 out of range 0..3"]),
])
def test_masks_arguments(res, kw, words):
    with pytest.raises(ParameterError) as exc:
        masks(res, SPEC, backend="numpy", **kw)
    _one_line(exc, *words)


@pytest.mark.parametrize("call, words", [
    (lambda r, m: masks(r, {"resolution": (10, 10)}), ["spec must be a RasterSpec", "dict"]),
    (lambda r, m: masks(r, "elegoo-mars-3"), ["spec must be a RasterSpec", "str"]),
    (lambda r, m: masks(m, SPEC), ["result must be a SliceResult", "Mesh"]),
    (lambda r, m: next(gpuslice.raster.iter_tiles(None, SPEC)), ["result must be a SliceResult"]),
    (lambda r, m: next(gpuslice.raster.iter_masks(r, SPEC, layers=[0.5])), ["whole layer indices"]),
])
def test_raster_arguments_of_the_wrong_kind(res, cube, call, words):
    """Were AttributeErrors ('dict' object has no attribute 'shape'); the generators check at their first step."""
    with pytest.raises(ParameterError) as exc:
        call(res, cube)
    _one_line(exc, *words)


@pytest.mark.parametrize("kw, words", [
    ({"spec": "elegoo"}, ["spec must be a RasterSpec"]), ({"settings": {"exposure": 1}}, ["settings must be a Print"]),
    ({"options": {"trap_grid": 1}}, ["options must be a CheckOptions"]), ({"bounds": (0, 0, 1)}, ["bounds must be"]),
    ({"backend": "bogus"}, ["unknown checks backend 'bogus'"]),                              # silently OpenCL
    ({"workers": "a"}, ["workers must be a whole number"]), ({"workers": 0}, ["workers must be"]),
    # a reversed box: "resolution must be two positive integers NXxNY, got (-46, -46)" named an argument not given
    ({"bounds": (10, 10, 0, 0)}, ["bounds must be (xmin, ymin, xmax, ymax) with xmin <= xmax", "(10, 10, 0, 0)"]),
])
def test_run_checks_arguments(res, kw, words):
    with pytest.raises(ParameterError) as exc:
        run_checks(res, **kw)
    _one_line(exc, *words)


def test_run_checks_result_and_options_types(cube):
    with pytest.raises(ParameterError) as exc:
        run_checks(cube)
    _one_line(exc, "result must be a SliceResult", "Mesh")
    with pytest.raises(ParameterError):  # True was a 1 mm grid
        CheckOptions(trap_grid=True)


def test_export_arguments(res, tmp_path):
    for call, words in ((lambda: formats.export(res, None), ["path must be a file path"]),
                        (lambda: formats.export(None, tmp_path / "x.svg"), ["result must be a SliceResult"]),
                        (lambda: formats.export(res, tmp_path), [str(tmp_path), "is a directory"])):
        with pytest.raises(ParameterError) as exc:
            call()
        _one_line(exc, *words)
    assert list(tmp_path.iterdir()) == []


def test_print_settings_flag_and_messages():
    """per_layer_settings='no' was True (a non-empty string); exposure='2' said 'got 2', as if it were a number."""
    with pytest.raises(ParameterError) as exc:
        PrintSettings(per_layer_settings="no")
    _one_line(exc, "per_layer_settings must be True or False", "'no'")
    with pytest.raises(ParameterError) as exc:
        PrintSettings(exposure="2")
    _one_line(exc, "exposure must be > 0, got '2'")
    assert PrintSettings(per_layer_settings=np.bool_(True)).per_layer_settings


# ---- the display and the resin options (raster/spec.py) ------------------------------------------------------------
@pytest.mark.parametrize("kw, words", [
    ({"mirror_x": "no"}, ["mirror_x must be True or False"]),            # was taken as True
    ({"keep_xy": "yes"}, ["keep_xy must be True or False"]),
    ({"portrait": 2}, ["portrait must be True or False"]),
    ({"pixel": True}, ["pixel must be a positive number"]),              # was a 1 mm pixel
    ({"gamma": True}, ["gamma must be a number"]),
    ({"gamma": "1"}, ["gamma must be a number"]),                        # TypeError
    ({"resolution": (True, True)}, ["resolution must be two positive integers"]),
    ({"resolution": "3840x2400"}, ["resolution must be two positive integers"]),  # ValueError: unpack
    ({"resolution": (3840,)}, ["resolution must be two positive integers"]),
    ({"pixel_y": "a"}, ["pixel_y must be a positive number"]),           # TypeError
])
def test_raster_spec_of_the_wrong_kind(kw, words):
    from gpuslice.raster import RasterSpec

    with pytest.raises(ParameterError) as exc:
        RasterSpec(**kw)
    _one_line(exc, *words)


def test_raster_spec_takes_numpy_numbers():
    """A float32 pixel (from an array of presets) was refused; numpy numbers are stored as Python ones."""
    from gpuslice.raster import RasterSpec

    spec = RasterSpec(resolution=(np.int64(1920), np.int32(1080)), pixel=np.float32(0.05), pixel_y=np.float64(0.06))
    assert spec.resolution == (1920, 1080) and type(spec.resolution[0]) is int
    assert type(spec.pixel) is float and spec.py == 0.06


@pytest.mark.parametrize("kw, words", [
    ({"printer": 5}, ["printer must be text"]),                          # AttributeError: 'int' has no 'lower'
    ({"job_name": 5}, ["job_name must be text"]),                        # TypeError
    ({"supersample": 2.5}, ["supersample must be a whole number"]),      # accepted
    ({"z_samples": 2.5}, ["z_samples must be a whole number"]),          # accepted
    ({"workers": True}, ["workers must be a whole number"]),             # one worker
    ({"png_level": "1"}, ["png_level must be a whole number"]),          # TypeError
])
def test_resin_options_of_the_wrong_kind(kw, words):
    from gpuslice.raster.spec import ResinOptions

    with pytest.raises(ParameterError) as exc:
        ResinOptions(**kw)
    _one_line(exc, *words)


def test_runs_and_adaptive_schedules_called_directly(res, cube):
    """layer_runs(res, "x") was an AttributeError ('str' has no 'gamma'); cusp_schedule(max_cusp="a") a numpy
    TypeError, smooth=True a smoothing of 1 mm per mm; adaptive_schedule(mesh, None) an AttributeError."""
    from gpuslice.raster.runs import layer_runs
    from gpuslice.schedule.adaptive import adaptive_schedule, cusp_schedule

    for call, words in (
        (lambda: layer_runs(res, "x"), ["spec must be a RasterSpec", "str"]),
        (lambda: layer_runs(res, SPEC, layers=[0.5]), ["whole layer indices"]),
        (lambda: cusp_schedule(cube, max_cusp="a"), ["max_cusp must be a number"]),
        (lambda: cusp_schedule(cube, smooth=True), ["smooth must be a number"]),
        (lambda: cusp_schedule(cube, resolution=-1.0), ["resolution must be a positive number"]),
        (lambda: adaptive_schedule(cube, None), ["params must be a SliceParams"]),
    ):
        with pytest.raises(ParameterError) as exc:
            call()
        _one_line(exc, *words)
    assert len(cusp_schedule(cube).z) > 0


@pytest.mark.parametrize(("call", "words"), [
    (lambda m: gpuslice.roi_schedule(m, ladder=("a",)), ("roi_ladder", "'a'")),
    (lambda m: gpuslice.roi_schedule(m, ladder=1.0), ("roi_ladder", "1.0")),
    (lambda m: gpuslice.roi_schedule(m, threshold="x"), ("roi_threshold", "'x'")),
    (lambda m: gpuslice.roi_schedule(m, quantile="x"), ("roi_quantile", "'x'")),
    (lambda m: gpuslice.roi_schedule(m, max_windows=1.5), ("roi_windows", "whole number", "1.5")),
    (lambda m: gpuslice.roi_schedule(m, min_layers="x"), ("roi_min_layers", "'x'")),
    (lambda m: gpuslice.roi_schedule(m, min_layers=-5), ("roi_min_layers", ">= 1", "-5")),
    (lambda m: gpuslice.adaptive_schedule(m, SliceParams(adaptive="roi")), ("gpuslice.roi_schedule", "slicer")),
    (lambda m: gpuslice.cusp_schedule("part.stl"), ("cusp_schedule takes a gpuslice Mesh", "load_mesh", "str")),
    (lambda m: gpuslice.roi_schedule("part.stl"), ("roi_schedule takes a gpuslice Mesh", "str")),
    (lambda m: gpuslice.mesh_repairs("part.stl"), ("mesh_repairs takes a gpuslice Mesh", "str")),
    (lambda m: gpuslice.cusp_schedule(m, resolution=1e-7), ("resolution must be at least", "1e-07")),
])
def test_adaptive_schedule_arguments(cube, call, words):
    """A ValueError, TypeError, UFuncTypeError or AttributeError from inside, "'NoneType' object is not callable",
    a MemoryError of 36 GiB (resolution 1e-7 mm), or a negative min_layers taken as it was."""
    with pytest.raises(ParameterError) as exc:
        call(cube)
    _one_line(exc, *words)


def test_a_max_height_above_the_model_does_not_loop_over_it(cube):
    """max_height=1e6 mm made a million-bin loop (minutes, gigabytes: killed after 11 minutes on nefertiti); no
    layer is taller than the model, so it is the same schedule as max_height = the model's height."""
    a = gpuslice.cusp_schedule(cube, max_height=1e6, min_height=0.05, resolution=0.01)
    b = gpuslice.cusp_schedule(cube, max_height=10.0, min_height=0.05, resolution=0.01)
    assert np.array_equal(a.z, b.z) and np.array_equal(a.thickness, b.thickness) and a.z.size == 1


def test_a_device_spec_string_is_taken_or_refused_whatever_the_size(cube):
    """load_mesh(path, device="0:0") and cusp_schedule(mesh, device="0:0") raised AttributeError on large meshes
    (a string has no .queue) and ignored the argument on small ones."""
    from gpuslice.errors import DeviceError

    for call in (lambda d: gpuslice.mesh_from_triangles(TRI, device=d),
                 lambda d: gpuslice.cusp_schedule(cube, device=d)):
        with pytest.raises(DeviceError, match=r"device '99:99' not found"):
            call("99:99")
    assert gpuslice.cusp_schedule(cube, device="0:0").z.size == gpuslice.cusp_schedule(cube).z.size


@pytest.mark.parametrize(("kw", "words"), [
    ({"z": [1.0, 2.0], "thickness": 0.5}, ("thickness shapes the layers, which z= gives already",)),
    ({"z": [1.0, 2.0], "adaptive": "cusp"}, ("adaptive shapes the layers, which z= gives already",)),
    ({"adaptive": "cusp", "thickness": 0.3}, ("thickness shapes uniform layers, not adaptive 'cusp' ones",)),
    ({"max_cusp": 0.3}, ("max_cusp shapes adaptive 'cusp' layers", "add adaptive='cusp'")),
    ({"adaptive": "area", "roi_ladder": (1.0, 0.5)}, ("roi_ladder shapes adaptive 'roi' layers",)),
])
def test_slice_mesh_refuses_an_option_its_layers_would_ignore(cube, kw, words):
    """Each was dropped without a word (the command line refuses the same flags)."""
    with pytest.raises(ParameterError) as exc:
        gpuslice.slice_mesh(cube, backend="numpy", **kw)
    _one_line(exc, *words)


def test_slice_mesh_takes_the_options_of_its_layers(cube):
    assert gpuslice.slice_mesh(cube, backend="numpy", thickness=2.5).n_layers == 4
    assert gpuslice.slice_mesh(cube, backend="numpy", z=[1.0, 2.0], layer_thickness=0.5).n_layers == 2
    assert gpuslice.slice_mesh(cube, backend="numpy", adaptive="cusp", max_cusp=0.1).n_layers > 0


@pytest.mark.parametrize(("kw", "bottom"), [
    ({"z": [1.0, 2.0, 3.0], "layer_thickness": 0.1}, [0.95, 1.95, 2.95]),  # were [0, 0.1, 0.2]: far from the planes
    ({"z": [-1.0, 5.0]}, [-4.0, 2.0]),                                      # were [0, 6]: neither plane in its slab
    ({"z": [1.0, 2.0, 4.0]}, [0.0, 1.5, 3.0]),                               # tiling from the bed: kept
    ({"z": [-1.0, 1.0, 10.0]}, [-2.0, 0.0, 5.5]),                            # from_z's own slabs, from below the bed
    ({"thickness": 2.5}, [0.0, 2.5, 5.0, 7.5]),
])
def test_each_layer_slab_holds_its_plane(cube, kw, bottom):
    """The exports (3MF ztop, CLI $$LAYER, SVG, GeoJSON) state each layer's slab from ``bottom``: explicit planes got
    slabs tiled from the bed whatever the planes, so a plane at z = 2 mm was written as the layer at 0.1-0.2 mm."""
    r = gpuslice.slice_mesh(cube, backend="numpy", **kw)
    np.testing.assert_allclose(r.bottom, bottom)
    assert np.all(r.bottom <= r.z + 1e-12) and np.all(r.z <= r.bottom + r.thickness + 1e-12)


def test_small_api_edges_from_the_audit(cube, res):
    """z beyond float32 leaked numpy's overflow RuntimeWarning; an (F, 3, 3) array was refused without pointing to
    mesh_from_triangles; np.array(0.5) was no thickness; to_shapely(open_chains="yes") was taken as True."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ParameterError) as exc:
            gpuslice.slice_mesh(cube, z=[1.0, 1e40], backend="numpy")
        _one_line(exc, "cutting planes must lie within 1e18 mm of the bed", "1e+40")
    with pytest.raises(ParameterError) as exc:
        gpuslice.slice_mesh(TRI, thickness=2.5, backend="numpy")
    _one_line(exc, "gpuslice.mesh_from_triangles")
    a = gpuslice.slice_mesh(cube, thickness=np.array(2.5), backend="numpy")
    assert np.array_equal(a.z, res.z) and a.meta["params"]["thickness"] == 2.5
    for call in (lambda: res.to_shapely(open_chains="yes"), lambda: res.layer(0).to_shapely(open_chains=1)):
        with pytest.raises(ParameterError) as exc:
            call()
        _one_line(exc, "open_chains must be True or False")


def test_values_a_second_helper_found_are_refused_or_handled(cube):
    """A sweep of the Python API with warnings as errors: each of these gave a wrong result without a word, an
    exception that was not gpuslice's, or a numpy warning."""
    from gpuslice.raster.settings import PrintSettings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # --fit 5e-324: the factor underflowed to 0, every vertex at the origin ("the model is 0 mm tall")
        with pytest.raises(gpuslice.InvalidGeometryError) as exc:
            gpuslice.mesh_from_triangles(TRI, fit=5e-324)
        _one_line(exc, "fit 4.94e-324 mm shrinks the mesh")
        # a first layer of 5e-324 or 1e-300 mm was cut on the bed in float32: a layer of no area
        for h0 in (5e-324, 1e-300):
            with pytest.raises(ParameterError) as exc:
                gpuslice.slice_mesh(cube, thickness=2.5, first_layer=h0, backend="numpy")
            _one_line(exc, "first_layer must be at least 1e-06 mm")
        # integers beyond a float: np.isfinite's TypeError; and shown by their length, not 302 digits
        assert gpuslice.slice_mesh(cube, thickness=2**1000, backend="numpy").n_layers == 0  # (above the top)
        with pytest.raises(ParameterError) as exc:
            gpuslice.slice_mesh(cube, adaptive="cusp", min_height=2**1000, backend="numpy")
        _one_line(exc, "max_height must be >= min_height (10715086… (302 digits) mm)")
        with pytest.raises(gpuslice.InvalidGeometryError) as exc:
            gpuslice.mesh_from_triangles(TRI, fit=2**1000)
        _one_line(exc, "overflow float32 arithmetic")
        # planes and thicknesses beyond 1e18 mm: warnings in from_z; a result whose volume overflowed and whose .npz
        # did not load
        for kw in ({"z": [1.0, np.inf]}, {"z": [1.0, 1e308]}, {"z": [1.0, 2.0], "layer_thickness": 1e308}):
            with pytest.raises(ParameterError) as exc:
                gpuslice.slice_mesh(cube, backend="numpy", **kw)
            _one_line(exc, "schedule:", "1e18" if "layer_thickness" not in kw else "at most 1e+18 mm")
        # an exposure of 5e-324 s passed "> 0" and was written as 0.0 into the archives' float32 fields
        for name in ("exposure", "bottom_exposure"):
            with pytest.raises(ParameterError) as exc:
                PrintSettings(**{name: 5e-324})
            _one_line(exc, f"{name} must be at least 0.001 s")


def test_api_arguments_of_the_wrong_kind_name_their_parameter():
    """The second sweep's Python-API findings mended: each was an exception of Python's or numpy's (an
    AttributeError, a TypeError) or a warning, or was taken for something else ("no" as True)."""
    from gpuslice.device import DeviceError
    from gpuslice.mesh.shapes import icosphere
    from gpuslice.raster.settings import PrintSettings
    from gpuslice.raster.spec import gamma_lut, with_printer
    from gpuslice.schedule.adaptive import cusp_schedule

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for gamma in (-1, float("nan"), "x"):
            with pytest.raises(ParameterError) as exc:
                gamma_lut(gamma)
            _one_line(exc, "gamma must be a number >= 0")
        for name in (5, np.array(["a"])):
            with pytest.raises(ParameterError) as exc:
                with_printer(name)
            _one_line(exc, "printer must be a preset's name or a preset file")
        with pytest.raises(ParameterError) as exc:
            gpuslice.mesh_from_triangles(TRI, center="no")
        _one_line(exc, "center must be True or False")
        with pytest.raises(DeviceError) as exc:
            cusp_schedule(gpuslice.mesh_from_triangles(icosphere(10.0)), max_cusp=0.05, min_height=0.05,
                          max_height=0.3, device=0)
        _one_line(exc, "device must be text")
        for field_name in ("lift_height", "lift_speed", "retract_speed2", "wait_after_lift"):
            with pytest.raises(ParameterError) as exc:
                PrintSettings(**{field_name: None})
            _one_line(exc, f"{field_name} must be", "got None")
    assert PrintSettings(bottom_lift_speed=None).group(True)["lift_speed"] == PrintSettings().lift_speed


def test_more_of_the_second_sweep_mended(tmp_path):
    """max_cusp=1e308 (a divide overflow warning), a volume deviation against an empty reference (0 %, where no
    percentage exists), run_batch's workers (-1, NaN, 1.5, True ran; "2" was a TypeError)."""
    from gpuslice.batch.runner import run_batch
    from gpuslice.bench.quality import volume_deviation
    from gpuslice.errors import BatchError
    from gpuslice.mesh.shapes import icosphere, write_stl
    from gpuslice.schedule.adaptive import cusp_schedule

    ball = gpuslice.mesh_from_triangles(icosphere(10.0))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        loose = cusp_schedule(ball, max_cusp=1e308, min_height=0.05, max_height=0.3)
    assert np.allclose(loose.thickness[:-1], 0.3)  # (no cusp bound: every layer as thick as allowed)
    r = gpuslice.slice_mesh(ball, thickness=0.5, backend="numpy")
    empty = gpuslice.slice_mesh(ball, z=[100.0], backend="numpy")  # (one plane above the ball: no area)
    vd = volume_deviation(r, empty)
    assert vd["volume_deviation_pct"] is None and vd["volume_deviation_mm3"] == pytest.approx(r.volume, rel=1e-9)
    stl = tmp_path / "ball.stl"
    write_stl(icosphere(10.0), stl)
    for workers in (-1, float("nan"), 1.5, True, "2", 2**63):
        with pytest.raises(BatchError) as exc:
            run_batch([str(stl)], tmp_path / "out", workers=workers)
        _one_line(exc, "workers must be a whole number from 0 to 1024")
