"""The cloud service's nested options: their defaults are the service's effective values
(those of the flat ``CloudServiceConfig`` they replace), a bad value is refused where it is
declared with the field's name, and the service's command-line arguments build them."""

from __future__ import annotations

import dataclasses
from operator import attrgetter
from typing import Any

import pytest

from common.links import WireFormat
from services.cloud.__main__ import build_parser
from services.cloud.config import CloudConfig, MbpConfig
from services.cloud.runner import config_from_args, service_config
from services.cloud.service_config import (
    CloudServiceConfig,
    MbpScheduleConfig,
    OverloadConfig,
    ProcessConfig,
)

# Each setting of the flat configuration, where it nests now, and its default there.
FLAT_DEFAULTS: dict[str, tuple[str, Any]] = {
    "optimize_every_keyframes": ("schedule.every_keyframes", 25),
    "debounce_s": ("schedule.debounce_s", 0.5),
    "optimize_rest_factor": ("schedule.rest_factor", 1.0),
    "full_ba_every_keyframes": ("full_ba.every_keyframes", 100),
    "full_ba_quiet_s": ("full_ba.quiet_s", 0.0),
    "full_ba_at_shutdown_s": ("full_ba.at_shutdown_s", 30.0),
    "mbp_every_keyframes": ("mbp.every_keyframes", 0),
    "mbp_at_shutdown": ("mbp.at_shutdown", True),
    "mbp_keep_recent": ("mbp.keep_recent", 5),
    "mbp_settle_keyframes": ("mbp.settle_keyframes", 30),
    "mbp_after_full_ba": ("mbp.after_full_ba", True),
    "mbp_running_cover_ratio": ("mbp.running.cover_ratio", 0.8),
    "mbp_running_min_observations": ("mbp.running.min_observations", 1),
    "mbp_running_max_interval_s": ("mbp.running.max_interval_s", 1.5),
    "overload_busy": ("overload.busy", 0.9),
    "overload_clear": ("overload.clear", 0.6),
    "overload_window_s": ("overload.window_s", 10.0),
    "overload_publish_every_s": ("overload.publish_every_s", 5.0),
    "publish_every_s": ("map_view.publish_every_s", 0.5),
    "publish_rest_factor": ("map_view.publish_rest_factor", 10.0),
    "gt_every_s": ("map_view.gt_every_s", 5.0),
    "bandwidth_window_s": ("map_view.bandwidth_window_s", 120.0),
    "display_spacing_m": ("map_view.display_spacing_m", 0.0),
    "mission": ("store.mission", None),
    "output_every_s": ("store.output_every_s", 30.0),
    "optimizer_process": ("processes.optimizer_process", True),
    "optimizer_nice": ("processes.optimizer_nice", 0),
    "decode_workers": ("processes.decode_workers", 0),
    "word_group_level": ("word_group_level", 3),
    "wire": ("wire", WireFormat.CODED),
}


@pytest.mark.parametrize("flat", sorted(FLAT_DEFAULTS))
def test_every_nested_default_is_the_flat_one(flat: str) -> None:
    path, value = FLAT_DEFAULTS[flat]
    assert attrgetter(path)(CloudServiceConfig()) == value


def test_the_running_pass_is_the_shutdown_pass_with_the_running_overrides() -> None:
    """The pass while running had the shutdown pass's options (``CloudConfig.mbp``) with cover
    0.8, one observation and 1.5 s between kept keyframes; its own MbpConfig is exactly that."""
    service = CloudServiceConfig()
    shutdown = service.domain.mbp
    assert shutdown == MbpConfig() == CloudConfig().mbp
    old_running = dataclasses.replace(
        shutdown, cover_ratio=0.8, min_observations=1, max_interval_s=1.5
    )
    assert service.mbp.running == old_running
    assert service.mbp.running == MbpScheduleConfig().running


@pytest.mark.parametrize(
    ("build", "field"),
    [
        (lambda: MbpConfig(min_observations=0), "min_observations"),
        (
            lambda: MbpScheduleConfig(
                running=dataclasses.replace(MbpScheduleConfig().running, min_observations=0)
            ),
            "min_observations",
        ),
        (lambda: OverloadConfig(busy=0.5, clear=0.6), "clear"),
        (lambda: OverloadConfig(busy=1.5), "busy"),
        (lambda: OverloadConfig(window_s=0.0), "window_s"),
        (lambda: ProcessConfig(optimizer_nice=20), "optimizer_nice"),
        (lambda: ProcessConfig(decode_workers=-1), "decode_workers"),
    ],
)
def test_a_bad_nested_value_is_refused_naming_its_field(build: Any, field: str) -> None:
    with pytest.raises(ValueError, match=field):
        build()


def test_the_command_line_defaults_build_the_default_service_config() -> None:
    args = build_parser().parse_args(["--state-dir", "s"])
    assert service_config(config_from_args(args)) == CloudServiceConfig()


def test_the_command_line_options_land_in_their_groups() -> None:
    argv = ["--state-dir", "s", "--no-mbp", "--mbp-every", "40", "--no-full-ba"]
    argv += ["--no-incremental-ba", "--early-loop-candidates", "0", "--dashboard-port", "0"]
    argv += ["--overload-busy", "0.6", "--mission", "m2", "--output-every", "5", "--wire", "raw"]
    argv += ["--optimizer-nice", "10", "--decode-workers", "2"]
    cfg = service_config(config_from_args(build_parser().parse_args(argv)))
    assert not cfg.domain.mbp.enabled and cfg.mbp.every_keyframes == 40
    assert not cfg.domain.full_ba.enabled and not cfg.domain.full_ba.incremental
    assert cfg.domain.place_recognition.early_candidates == 0
    assert cfg.map_view.publish_every_s == 0.0
    assert cfg.overload.busy == 0.6 and cfg.overload.clear == pytest.approx(0.4)
    assert cfg.store.mission == "m2" and cfg.store.output_every_s == 5.0
    assert cfg.wire is WireFormat.RAW
    assert cfg.processes.optimizer_nice == 10 and cfg.processes.decode_workers == 2
    assert cfg.mbp.running == MbpScheduleConfig().running  # no flag changes the running pass
