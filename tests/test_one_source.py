"""One source per value: node parameters, bev-bag flags and shipped configs agree with the
dataclasses that own the defaults; one grid tolerance; a weights file is read once at start-up."""

from __future__ import annotations

import math
from dataclasses import MISSING, fields, replace
from pathlib import Path
from types import SimpleNamespace

import pytest
import yaml

from bags.cli.main import build_parser
from bags.cli.synth import SynthBagOptions
from bags.io.reader import DEFAULT_SYNC
from bags.io.writer import STORAGES
from bags.replay import ReplayOptions
from bev_mapper_core.errors import GridError
from bev_mapper_core.geometry.grid import GRID_TOL_M, BevGrid
from bev_mapper_core.geometry.rig import PRESETS
from bev_mapper_core.geometry.time_placement import TimePlacementConfig
from bev_mapper_core.mapper import INPUT_KINDS, MapperConfig, available_methods
from bev_mapper_core.metrics import SCOPES
from bev_mapper_core.synth.config import SynthConfig
from bev_mapper_core.synth.styles import STYLE_CHOICES
from bev_mapper_core.temporal import TemporalConfig
from bev_mapper_ros.config import (
    PARAM_FIELDS,
    NodeConfig,
    node_config_from_params,
)
from bev_mapper_ros.rig_params import CONFIG_DIR
from msg_adapters import GridMessageError, SyncConfig, check_grid_info

# ------------------------------------------------------------ node parameters
_OWNED_ELSEWHERE = {"mapper", "grid", "extrinsics", "ego_masks", "temporal", "time_placement"}  # nested dataclasses / per-camera parameters


def _owner_field(name: str):
    """The dataclass field a parameter sets, found by name (independently of PARAM_FIELDS)."""
    if name.startswith("grid."):
        owner, fname = BevGrid, name.split(".", 1)[1]
    elif name.startswith("temporal_"):
        owner, fname = TemporalConfig, name.split("_", 1)[1]
    elif name.startswith("time_placement"):
        owner, fname = TimePlacementConfig, name[len("time_placement_"):] or "mode"
    elif name in {f.name for f in fields(NodeConfig)}:
        owner, fname = NodeConfig, name
    else:
        owner, fname = MapperConfig, name
    return next(f for f in fields(owner) if f.name == fname)


def _expected_declared(f):
    default = f.default_factory() if f.default_factory is not MISSING else f.default
    if f.name in ("cameras", "classes"):  # string arrays: declared typed without a value when empty/required
        return list(default) if default not in (MISSING, None) and default else None
    return "" if default is None else default


def test_parameter_table_defaults_are_the_dataclass_defaults():
    """Each declared default equals its dataclass field's default (value and Python type)."""
    from rcl_interfaces.msg import ParameterType as T

    from bev_mapper_ros.config import RUNTIME_PARAMETERS
    from bev_mapper_ros.params import PARAMETERS

    py_type = {T.PARAMETER_STRING: str, T.PARAMETER_BOOL: bool, T.PARAMETER_INTEGER: int,
               T.PARAMETER_DOUBLE: float, T.PARAMETER_STRING_ARRAY: list}
    assert list(PARAMETERS) == list(PARAM_FIELDS)
    for name, (default, ptype, read_only, text) in PARAMETERS.items():
        want = _expected_declared(_owner_field(name))
        assert default == want and type(default) is type(want), name
        assert default is None or type(default) is py_type[ptype], name
        assert read_only == (name not in RUNTIME_PARAMETERS) and text, name
    # run-time parameters are NodeConfig fields (diagnostics), never what shapes the mapper
    assert {PARAM_FIELDS[n].owner for n in RUNTIME_PARAMETERS} == {NodeConfig}


def test_every_scalar_field_is_a_parameter():
    declared = {(pf.owner, pf.field) for pf in PARAM_FIELDS.values()}
    for owner in (NodeConfig, MapperConfig, BevGrid):
        for f in fields(owner):
            if owner is NodeConfig and f.name in _OWNED_ELSEWHERE:
                continue
            assert (owner, f.name) in declared, f"{owner.__name__}.{f.name} has no node parameter"
    # of the temporal fusion's settings, the node exposes the window (the rest keep their defaults)
    assert {(o, f) for o, f in declared if o is TemporalConfig} == {(TemporalConfig, "window")}
    # every setting of the time placement is one
    assert {f for o, f in declared if o is TimePlacementConfig} == {f.name for f in fields(TimePlacementConfig)}


def test_declared_defaults_give_the_dataclass_defaults():
    """What the node reads back from its declared defaults (placeholders dropped, as
    read_parameters does), and a dict with only the cameras, both give the dataclass defaults."""
    from bev_mapper_ros.params import PARAMETERS

    read_back = {n: v[0] for n, v in PARAMETERS.items()}
    read_back.update(cameras=["a"], classes=[])  # declared without a value: read back empty
    want = NodeConfig(cameras=("a",), mapper=MapperConfig())
    assert node_config_from_params(read_back) == want
    assert node_config_from_params({"cameras": ["a"]}) == want
    assert node_config_from_params({"cameras": ["a"], "rig": "front1"}).rig == "front1"


@pytest.mark.parametrize("rig", sorted(PRESETS))
def test_rig_alone_is_its_shipped_config(rig):
    """``rig`` alone gives the same configuration as the shipped config/<rig>.yaml (both come
    from the preset); explicit cameras / extrinsics override the preset's."""
    from bev_mapper_ros.config import preset_parameters

    params = yaml.safe_load((CONFIG_DIR / f"{rig}.yaml").read_text())["/**"]["ros__parameters"]
    flat = {k: v for k, v in params.items() if not isinstance(v, dict)}
    flat.update({f"extrinsics.{k}": v for k, v in params["extrinsics"].items()})
    alone, shipped = node_config_from_params({"rig": rig}), node_config_from_params(flat)
    assert replace(alone, extrinsics=()) == replace(shipped, extrinsics=())
    for cam in shipped.cameras:
        assert (alone.extrinsic(cam) == shipped.extrinsic(cam)).all(), cam
    assert preset_parameters(rig) == {k: v for k, v in flat.items() if k == "cameras" or k.startswith("extrinsics.")}
    first = params["cameras"][0]
    mine = node_config_from_params({"rig": rig, "cameras": [first], f"extrinsics.{first}": [0, 0, 1, 0, 0, 0, 1]})
    assert mine.cameras == (first,) and mine.extrinsic(first)[2, 3] == 1.0
    assert preset_parameters("mine") == {}

def test_sync_defaults_come_from_sync_config():
    cfg = NodeConfig(cameras=("a",))
    assert cfg.sync_slop_s == SyncConfig.slop_ns / 1e9 and cfg.sync_timeout_s == SyncConfig.timeout_ns / 1e9
    assert cfg.sync_config() == SyncConfig()
    assert replace(cfg, sync_slop_s=0.07, sync_timeout_s=0.3).sync_config() == SyncConfig(
        slop_ns=70_000_000, timeout_ns=300_000_000)
    # Bag replay groups sets with the node's window (so it maps the sets the node maps) and
    # waits longer for missing cameras (offline, waiting costs nothing).
    assert DEFAULT_SYNC == SyncConfig.replay()
    assert DEFAULT_SYNC.slop_ns == SyncConfig.slop_ns and DEFAULT_SYNC.timeout_ns > SyncConfig.timeout_ns
    assert DEFAULT_SYNC.queue_size >= SyncConfig.queue_size


@pytest.mark.parametrize("rig", sorted(PRESETS))
def test_shipped_config_keys_are_declared_parameters(rig):
    """config/<rig>.yaml (generated, see test_node_config) only sets declared parameters and
    gives a valid NodeConfig on the standard grid."""
    params = yaml.safe_load((CONFIG_DIR / f"{rig}.yaml").read_text())["/**"]["ros__parameters"]
    flat = {}
    for key, value in params.items():
        if isinstance(value, dict):
            flat.update({f"{key}.{k}": v for k, v in value.items()})
        else:
            flat[key] = value
    extrinsics = {k for k in flat if k.startswith("extrinsics.")}
    assert set(flat) - extrinsics <= set(PARAM_FIELDS)
    assert extrinsics == {f"extrinsics.{c}" for c in flat["cameras"]}
    cfg = node_config_from_params(flat)
    assert cfg.rig == rig and cfg.grid.isclose(BevGrid()) and cfg.mapper.input_kind == MapperConfig.input_kind


# ------------------------------------------------------------------ bev-bag
def _sub(name: str):
    sub = next(a for a in build_parser()._actions if a.dest == "command")
    return sub.choices[name]


def _action(parser, flag: str):
    return next(a for a in parser._actions if flag in a.option_strings)


def test_bev_bag_choices_come_from_the_constants():
    replay, synth = _sub("replay"), _sub("synth")
    assert tuple(_action(replay, "--method").choices) == available_methods()
    assert tuple(_action(replay, "--input").choices) == INPUT_KINDS
    assert tuple(_action(replay, "--scope").choices) == SCOPES
    assert tuple(_action(replay, "--storage").choices) == STORAGES
    rig = _action(synth, "--rig")  # a preset or random-<seed>: its type checks, its help names the presets
    assert rig.type("random-7") == "random-7" and all(rig.type(p) == p for p in PRESETS)
    assert all(p in rig.help for p in PRESETS)
    assert tuple(_action(synth, "--style").choices) == STYLE_CHOICES
    assert tuple(_action(synth, "--storage").choices) == STORAGES
    # --label-map takes a preset or a YAML path: no choices, but the help names every preset
    from bev_mapper_core.labels.label_maps import PRESET_NAMES

    label_map = _action(replay, "--label-map")
    assert label_map.default == MapperConfig.label_map == PRESET_NAMES[0]
    assert all(name in label_map.help for name in PRESET_NAMES)
    # every input kind has a bag topic and a default node topic
    from bags.io.topics import IMAGE_KINDS
    from bev_mapper_ros.config import DEFAULT_TOPICS

    assert set(IMAGE_KINDS) == set(INPUT_KINDS) == set(DEFAULT_TOPICS)


def test_bev_bag_defaults_are_the_dataclass_defaults():
    """No flags given = the dataclasses' defaults."""
    from bags.cli import replay as replay_cmd
    from bags.cli import synth as synth_cmd

    opts = replay_cmd.options_from_args(build_parser().parse_args(["replay", "b", "--out", "o"]))
    assert opts == ReplayOptions(bag=Path("b"), out=Path("o"), progress=opts.progress)
    assert opts.mapper == MapperConfig()
    opts = synth_cmd.options_from_args(build_parser().parse_args(["synth", "o"]))
    assert opts == SynthBagOptions(out=Path("o"))
    assert opts.synth == SynthConfig() and opts.grid == BevGrid()


# --------------------------------------------------------------- grid equality
def test_grid_isclose_has_one_documented_tolerance():
    g = BevGrid()
    near = replace(g, x_min=g.x_min + GRID_TOL_M / 2, y_max=g.y_max - GRID_TOL_M / 2)
    far = replace(g, x_min=g.x_min + 3 * GRID_TOL_M)
    assert near != g and near.isclose(g) and g.isclose(near)
    assert not far.isclose(g) and far.isclose(g, tol=5 * GRID_TOL_M)
    assert not replace(g, x_max=g.x_max + g.resolution).isclose(g)  # one more cell
    assert not g.isclose("not a grid")
    assert hash(g) == hash(BevGrid())  # == / hash stay the exact dataclass ones


def test_grid_dict_round_trip():
    g = BevGrid(-10.0, 20.0, -5.0, 5.0, 0.5)
    assert list(g.to_dict()) == [f.name for f in fields(BevGrid)]
    assert BevGrid.from_dict(g.to_dict()) == g
    with pytest.raises(GridError, match="missing"):
        BevGrid.from_dict({"x_min": 0.0})
    with pytest.raises(GridError, match="numbers"):
        BevGrid.from_dict({**g.to_dict(), "resolution": "fine"})


def _info(grid: BevGrid, dx: float = 0.0):
    origin = SimpleNamespace(position=SimpleNamespace(x=grid.x_min + dx, y=grid.y_min, z=0.0),
                             orientation=SimpleNamespace(x=0.0, y=0.0, z=0.0, w=1.0))
    return SimpleNamespace(resolution=grid.resolution, width=grid.width, height=grid.height, origin=origin)


def test_bag_grid_check_and_weights_check_share_the_tolerance():
    """A grid within GRID_TOL_M of another is the same grid for the bag reader (GT layers) and
    for the weights check; a bit more is not, for both."""
    from bev_mapper_core.methods.bimapper.mapper import default_weights_path
    from bev_mapper_core.methods.bimapper.weights import WeightsFile
    from bev_mapper_core.nn.weights import WeightsError

    wf = WeightsFile.open(default_weights_path("front1", "labels"))
    stored = wf.grid
    inside = replace(stored, x_min=stored.x_min + GRID_TOL_M / 2)
    outside = replace(stored, x_min=stored.x_min + 3 * GRID_TOL_M)
    check_grid_info(_info(stored, GRID_TOL_M / 2), stored)
    wf.check(grid=inside)
    with pytest.raises(GridMessageError, match="origin"):
        check_grid_info(_info(stored, 3 * GRID_TOL_M), stored)
    with pytest.raises(WeightsError, match="weights were trained for grid"):
        wf.check(grid=outside)
    assert math.isclose(GRID_TOL_M, 1e-6)


# ----------------------------------------------------- weights read once
class _CountingSafeOpen:
    """Wraps ``safe_open``: counts opens, metadata reads and handles that read tensors."""

    def __init__(self, real):
        self.real, self.opens, self.metadata_reads, self.tensor_handles = real, 0, 0, 0

    def __call__(self, *args, **kwargs):
        self.opens += 1
        counter, handle = self, self.real(*args, **kwargs)

        class Handle:
            def __enter__(self):
                self.f = handle.__enter__()
                self.read_tensors = False
                return self

            def __exit__(self, *exc):
                counter.tensor_handles += self.read_tensors
                return handle.__exit__(*exc)

            def metadata(self):
                counter.metadata_reads += 1
                return self.f.metadata()

            def get_tensor(self, name):
                self.read_tensors = True
                return self.f.get_tensor(name)

            def __getattr__(self, name):
                return getattr(self.f, name)

        return Handle()


def test_node_start_up_reads_the_weights_file_once(monkeypatch):
    """preflight then create_mapper (what the node does): one header read, one tensor read."""
    from bev_mapper_core.geometry.rig import preset_rig
    from bev_mapper_core.mapper import create_mapper, preflight
    from bev_mapper_core.methods.bimapper import weights
    from bev_mapper_core.nn import weights as generic

    counter = _CountingSafeOpen(generic.safe_open)
    monkeypatch.setattr(generic, "safe_open", counter)
    weights.WeightsFile.clear_cache()
    rig, grid, cfg = preset_rig("front1"), BevGrid(), MapperConfig(threads=1)
    preflight(cfg, rig.name, grid, rig.names)
    mapper = create_mapper(rig, grid, cfg)
    assert (counter.metadata_reads, counter.tensor_handles, counter.opens) == (1, 1, 2)
    assert mapper.model is not None


def test_weights_cache_sees_a_replaced_file(tmp_path, monkeypatch):
    from bev_mapper_core.methods.bimapper import weights
    from bev_mapper_core.methods.bimapper.mapper import default_weights_path
    from bev_mapper_core.nn import weights as generic

    src = default_weights_path("front1", "labels")
    path = tmp_path / "w.safetensors"
    path.write_bytes(src.read_bytes())
    counter = _CountingSafeOpen(generic.safe_open)
    monkeypatch.setattr(generic, "safe_open", counter)
    assert weights.WeightsFile.open(path).rig_name == "front1"
    assert weights.WeightsFile.open(path).rig_name == "front1"
    assert counter.metadata_reads == 1
    path.write_bytes(b"not safetensors")  # replaced: read again, and rejected
    with pytest.raises(weights.WeightsError, match="safetensors"):
        weights.WeightsFile.open(path)
