"""The generated command line: every field an option, presets under explicit values."""

import argparse

import pytest

from urhead.config import FIT_PRESETS, FitConfig, add_arguments, from_arguments
from urhead.errors import InvalidArgumentError


def parse(argv, preset=None):
    parser = argparse.ArgumentParser()
    add_arguments(parser, FitConfig)
    return from_arguments(FitConfig, parser.parse_args(argv), FIT_PRESETS, preset)


def test_defaults_are_the_papers():
    c = parse([])
    assert (c.iterations, c.uv_resolution, c.sh_degree, c.prune_opacity, c.depth_eps) == (
        50_000,
        2048,
        3,
        0.01,
        0.01,
    )
    assert (c.lr_color, c.lr_normal, c.lr_scale, c.lr_opacity, c.lr_displacement) == (
        5e-4,
        1e-3,
        5e-3,
        5e-2,
        1e-5,
    )
    assert (c.lr_expression, c.lr_pose, c.lr_translation) == (1e-3, 1e-5, 1e-6)


def test_explicit_options_override_the_preset():
    c = parse(["--uv-resolution", "256", "--no-gaussians", "--sampling", "uniform"], "quick")
    assert c.uv_resolution == 256  # explicit beats preset
    assert c.iterations == FIT_PRESETS["quick"]["iterations"]  # preset beats default
    assert c.gaussians is False and c.sampling == "uniform"


@pytest.mark.parametrize(
    ("argv", "name"),
    [
        (["--sh-degree", "4"], "sh_degree"),
        (["--lr-color", "-1"], "lr_color"),
        (["--initial-gaussians", "50000", "--max-gaussians", "10"], "max_gaussians"),
    ],
)
def test_out_of_range_values_are_named(argv, name):
    with pytest.raises(InvalidArgumentError, match=f"^{name} "):
        parse(argv)


def test_unknown_preset_is_rejected():
    with pytest.raises(InvalidArgumentError, match="preset"):
        parse([], "fast")


def test_literal_choices_are_enforced():
    parser = argparse.ArgumentParser()
    add_arguments(parser, FitConfig)
    with pytest.raises(SystemExit):
        parser.parse_args(["--sampling", "random"])
