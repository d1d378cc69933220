"""What the story demo of ``realgap demo`` runs: one typed configuration, saved as
``demo_out/demo_config.json`` (the command's flags are generated from it)."""
from __future__ import annotations

from dataclasses import dataclass

from data_tools.errors import ConfigError

__all__ = ["DemoConfig", "DEMO_PRESETS"]


@dataclass
class DemoConfig:
    """The three parts of the demo: the lab on a mystery sensor, exploration, recognition."""

    mystery_seed: int = 5
    """Seed of the mystery sensor: its scene, camera, trajectory and noise."""
    mystery_effect: str = "edge_fattening"
    """The effect the mystery sensor hides (one of :data:`synth.lab.mystery.EFFECTS`, or 'random': drawn
    from the seed); edge fattening is a block matcher's habit that the ideal model lacks entirely."""
    mystery_frames: int = 6
    """Frames of the mystery sequence (the lab diagnoses on 4 of them and checks on all)."""
    room_seed: int = 100_000
    """``procedural_room`` seed of the explored room (the neural model's first test room, never trained on)."""
    room_frames: int = 150
    """Frames of the room walk (30 frames/s; the neural backend registers every 10th)."""
    novel_frame: int = 95
    """Trajectory pose at which the TSDF and the neural memory render their novel views (not a multiple
    of 10: a frame the memory never wrote)."""
    recog_scans: int = 4
    """Test scans per embedded chair, by the ``structure`` sensor (the recogniser was trained on kinect_v1)."""
    recog_model: str = ""
    """Recogniser folder ('' = the one shipped in recog/weights/chairs)."""
    screenshot: bool = True
    """Render a viewer screenshot of the exploration (off-screen, EGL); off where no GL is available."""
    seed: int = 0
    """Seed of every simulation the demo runs besides the mystery sensor."""
    align: str = "auto"
    """Alignment of the exploration's absolute errors (ATE, APE), as ``realgap batch --align``: auto is SE(3)
    when a run's motion determines a rotation, else its first poses (the neural run has few poses)."""

    def validate(self) -> "DemoConfig":
        for name in ("mystery_frames", "room_frames", "recog_scans"):
            if int(getattr(self, name)) < 1:
                raise ConfigError(f"demo option {name} must be at least 1, got {getattr(self, name)}")
        if self.mystery_frames < 2:
            raise ConfigError(f"demo option mystery_frames must be at least 2, got {self.mystery_frames}")
        if self.room_frames < 30:
            raise ConfigError(f"demo option room_frames must be at least 30 (3 neural registrations), "
                              f"got {self.room_frames}")
        from synth.lab.mystery import EFFECTS
        if self.mystery_effect not in EFFECTS + ("random",):
            raise ConfigError(f"demo option mystery_effect must be one of {', '.join(EFFECTS)} or random, "
                              f"got {self.mystery_effect!r}")
        from slam.metrics import ALIGNERS
        if self.align not in ALIGNERS:
            raise ConfigError(f"demo option align must be one of {', '.join(ALIGNERS)}, got {self.align!r}")
        if not 0 <= self.novel_frame < self.room_frames:
            raise ConfigError(f"demo option novel_frame must be in 0..{self.room_frames - 1}, got {self.novel_frame}")
        return self


DEMO_PRESETS = {"default": DemoConfig(), "quick": DemoConfig(mystery_frames=4, room_frames=60, novel_frame=45,
                                                             recog_scans=2, screenshot=False)}
"""``default``: the story in about five minutes on 2 cores; ``quick``: the same story, smaller (tests)."""
