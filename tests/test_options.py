"""The Options base: validation on construction, TOML mapping, unknown keys."""

from __future__ import annotations

import dataclasses
from typing import Literal

import pytest

from satsweep.errors import InputError, OptionsError
from satsweep.options import Options, dumps_toml, load_toml


@dataclasses.dataclass(frozen=True)
class DemoOptions(Options):
    radius: int = 3  # a window radius in pixels
    eps: float = 1e-3  # a regulariser
    window: tuple[int, int] = (7, 9)  # a window size
    mode: Literal["a", "b"] = "a"  # a choice
    budget: int | None = None  # optional

    def check(self) -> None:
        self._require(self.radius >= 0, "radius", "must be >= 0")
        self._require(self.eps > 0, "eps", "must be > 0")


def test_defaults_are_valid_and_frozen():
    o = DemoOptions()
    with pytest.raises(dataclasses.FrozenInstanceError):
        o.radius = 4  # type: ignore[misc]


def test_check_names_the_field():
    with pytest.raises(OptionsError, match=r"DemoOptions\.radius = -1: must be >= 0"):
        DemoOptions(radius=-1)


@pytest.mark.parametrize(
    "kwargs, field",
    [({"radius": 2.5}, "radius"), ({"eps": "x"}, "eps"), ({"mode": "c"}, "mode"),
     ({"window": (7,)}, "window"), ({"radius": True}, "radius")],
)
def test_type_errors_name_the_field(kwargs, field):
    with pytest.raises(OptionsError, match=rf"DemoOptions\.{field}"):
        DemoOptions(**kwargs)


def test_from_mapping_converts_toml_types_and_rejects_unknown_keys():
    o = DemoOptions.from_mapping({"radius": 5, "eps": 1, "window": [3, 5]})
    assert o == DemoOptions(radius=5, eps=1.0, window=(3, 5))
    with pytest.raises(OptionsError, match="unknown key.*radious"):
        DemoOptions.from_mapping({"radious": 5}, source="cfg.toml")


def test_from_mapping_out_of_range_values_name_the_source():
    with pytest.raises(OptionsError, match=r"^cfg\.toml \[demo\]: DemoOptions\.radius = -2: must be >= 0$"):
        DemoOptions.from_mapping({"radius": -2}, source="cfg.toml [demo]")
    with pytest.raises(OptionsError, match=r"^cfg\.toml \[demo\]: DemoOptions\.mode"):
        DemoOptions.from_mapping({"mode": "c"}, source="cfg.toml [demo]")


def test_toml_round_trip(tmp_path):
    o = DemoOptions(radius=4, window=(5, 5), mode="b")
    path = tmp_path / "c.toml"
    path.write_text(dumps_toml({"demo": o.to_dict()}))
    assert DemoOptions.from_mapping(load_toml(path)["demo"]) == o


def test_bad_toml_names_the_file(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text("radius = = 3\n")
    with pytest.raises(InputError, match="broken.toml: not valid TOML"):
        load_toml(path)
    with pytest.raises(InputError, match="does not exist"):
        load_toml(tmp_path / "absent.toml")


def test_public_api_names_resolve():
    import satsweep

    for name in satsweep.__all__:
        assert getattr(satsweep, name) is not None, name
    with pytest.raises(AttributeError):
        satsweep.no_such_thing  # noqa: B018


def test_advanced_options_go_in_their_sub_table_and_round_trip(tmp_path):
    from satsweep.config import SECTIONS, PipelineConfig

    config = (PipelineConfig().override("dsm", outlier_m=3.0, resolution=1.0)
              .override("camera", grid_size=(50, 50, 10)))
    text = config.to_toml()
    assert "[dsm.advanced]" in text and "[camera.advanced]" in text
    # Each advanced option is written in the sub-table, each other one in the stage's table.
    import tomllib

    tables = tomllib.loads(text)
    for name, options in SECTIONS.items():
        advanced = tables[name].get("advanced", {})
        # TOML has no null: None is "none" for a number option, left out for a string one
        written = getattr(config, name).to_tables()
        written.update(written.pop("advanced", {}))
        unset = {k for k, v in written.items() if v is None}
        assert set(advanced) == set(options.ADVANCED) - unset
        assert not set(options.ADVANCED) & (set(tables[name]) - {"advanced"})
    path = tmp_path / "c.toml"
    path.write_text(text, encoding="utf-8")
    assert PipelineConfig.from_toml(path) == config


def test_advanced_option_accepted_in_the_table_but_a_basic_one_refused_in_advanced():
    from satsweep.config import PipelineConfig

    flat = PipelineConfig.from_mapping({"dsm": {"outlier_m": 3.0}})
    nested = PipelineConfig.from_mapping({"dsm": {"advanced": {"outlier_m": 3.0}}})
    assert flat == nested and flat.dsm.outlier_m == 3.0
    with pytest.raises(OptionsError, match=r"resolution not advanced option\(s\) of DSMOptions"):
        PipelineConfig.from_mapping({"dsm": {"advanced": {"resolution": 1.0}}})
    with pytest.raises(OptionsError, match="both in the table and in its 'advanced'"):
        PipelineConfig.from_mapping({"dsm": {"outlier_m": 3.0, "advanced": {"outlier_m": 2.0}}})


def test_every_advanced_name_is_a_field():
    import dataclasses

    from satsweep.config import SECTIONS

    for options in SECTIONS.values():
        assert set(options.ADVANCED) <= {f.name for f in dataclasses.fields(options)}


def test_a_retired_key_is_ignored_with_a_warning_naming_the_file_and_its_replacement(tmp_path):
    """An older run's config.toml (which wrote every option) still loads: a key satsweep no
    longer reads is dropped with a RetiredOptionWarning, in the table or its advanced
    sub-table; the rest of the file still applies, and unknown keys are still errors."""
    from satsweep.config import PipelineConfig, ReconstructOptions
    from satsweep.errors import RetiredOptionWarning

    assert {"tie_altitude_quantile", "tie_altitude_margin_m"} <= set(ReconstructOptions.RETIRED)
    path = tmp_path / "old.toml"
    path.write_text("[reconstruct]\ntile_m = 500.0\n[reconstruct.advanced]\n"
                    "tie_altitude_quantile = 0.01\ntie_altitude_margin_m = 20.0\n")
    with pytest.warns(RetiredOptionWarning) as caught:
        config = PipelineConfig.from_toml(path)
    messages = [str(w.message) for w in caught]
    assert len(messages) == 2 and all(str(path) in m and "sparse stage" in m for m in messages)
    assert config == PipelineConfig().override("reconstruct", tile_m=500.0)
    with pytest.warns(RetiredOptionWarning, match="tie_altitude_margin_m is no longer read"):
        PipelineConfig.from_mapping({"reconstruct": {"tie_altitude_margin_m": 5.0}})
    with pytest.raises(OptionsError, match="unknown key"):
        PipelineConfig.from_mapping({"reconstruct": {"tie_altitude_typo": 5.0}})


def test_the_command_line_prints_a_retired_key_as_a_satsweep_warning(tmp_path, capsys):
    from satsweep.cli import main

    path = tmp_path / "old.toml"
    path.write_text("[reconstruct]\ntie_altitude_quantile = 0.01\n")
    assert main(["config", "--config", str(path)]) == 0
    err = capsys.readouterr().err.splitlines()
    assert err == [f"satsweep: warning: {path} [reconstruct]: tie_altitude_quantile is no longer "
                   "read (the altitude range now comes from the sparse stage's adjusted tie "
                   "points; [sparse] altitude_margin_below_m and altitude_margin_above_m set its "
                   "margins); remove it"]


def test_none_of_a_number_option_round_trips_through_toml_as_the_string_none(tmp_path):
    """TOML has no null: a run's config.toml must repeat an option set to None (whose default is
    not None) instead of leaving it out and getting the default back."""
    from satsweep.config import PipelineConfig

    c = PipelineConfig()
    c = dataclasses.replace(c, mrf=c.mrf.replace(sgm_sweep_gf_radius=None),
                            sweep=c.sweep.replace(consensus_grad_weight=None))
    assert PipelineConfig().mrf.sgm_sweep_gf_radius is not None  # else the test proves nothing
    path = tmp_path / "run.toml"
    path.write_text(c.to_toml())
    assert 'sgm_sweep_gf_radius = "none"' in path.read_text()
    back = PipelineConfig.from_toml(path)
    assert back == c and back.mrf.sgm_sweep_gf_radius is None
    # a string option keeps "none" as a string (and is refused where a choice is expected)
    assert DemoOptions.from_mapping({"budget": "none"}).budget is None
    with pytest.raises(OptionsError, match="mode"):
        DemoOptions.from_mapping({"mode": "none"})
