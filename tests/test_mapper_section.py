"""The mapper takes its [mapper] section as it is: `SemanticMap.from_config` keeps the section
(nothing renamed, the back-end's sub-section the same object), and the library's keyword form is
checked by that same section, so the library and the config refuse the same values with the same
one line."""

from __future__ import annotations

import pytest

from smana.common.config import ConfigError, SmanaConfig
from smana.common.config.mapper import RESOLUTION_RANGE_M, MapperConfig, max_range_for
from smana.services.mapper import mapfile
from smana.services.mapper.block_grid import KEY_LIMIT
from smana.services.mapper.semantic_map import SemanticMap


def test_from_config_keeps_the_section_as_it_is():
    cfg = SmanaConfig.load(None, ["mapper.backend=tsdf", "mapper.raycast_range_m=0"])
    m = SemanticMap.from_config(cfg.mapper)
    assert m.section is cfg.mapper and m.config is cfg.mapper.tsdf
    assert (m.resolution_m, m.max_range_m, m.raycast_range_m) == (0.1, 10.0, 0.0)
    kw = SemanticMap("tsdf", 0.1, 10.0, 0.0)  # the keyword form: the same section, rebuilt
    assert kw.section == cfg.mapper


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"resolution_m": 0.005}, "mapper.resolution_m: at least 0.01 m, got 0.005"),
        ({"resolution_m": 20.0}, "mapper.resolution_m: expected a number <= 10, got 20.0"),
        ({"max_range_m": 1e6}, "mapper.max_range_m: must be in (0, 13107.2] at resolution_m 0.1"),
        ({"raycast_range_m": -1.0}, "mapper.raycast_range_m: expected a number >= 0, got -1.0"),
        ({"max_range_m": float("nan")}, "mapper.max_range_m: expected a finite number"),
    ],
)
def test_the_library_and_the_config_refuse_the_same_values_in_one_line(kwargs, message):
    for make in (lambda: MapperConfig(**kwargs), lambda: SemanticMap("octree-max", **kwargs)):
        with pytest.raises(ConfigError) as info:
            make()
        assert str(info.value).startswith(message) and "\n" not in str(info.value)


def test_one_set_of_limits_for_the_config_the_grid_and_the_files():
    assert KEY_LIMIT == 32768 and max_range_for(0.1) == pytest.approx(4 * KEY_LIMIT * 0.1)
    assert mapfile.max_range_for is max_range_for
    SemanticMap("octree-max", RESOLUTION_RANGE_M[0], max_range_for(RESOLUTION_RANGE_M[0]))
    SemanticMap("octree-max", RESOLUTION_RANGE_M[1])  # both ends are fine
