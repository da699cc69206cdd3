"""Pictures of one episode: a top-down PNG of how it ended and an animated GIF of how it went.

Numbers in a results table say how often a policy fails, not how; a picture of the episode shows
whether the robot clipped a wall, was run down by an obstacle or circled near the target. The
episode is recorded once (`record_episode`) and drawn from the record, so the PNG and the GIF show
the same run and drawing never steps the simulator.

Plotting is an optional extra (`qnav[viz]`): matplotlib and pillow are imported only when a
picture is drawn, so the car's base install can import this module without them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from qnav.contracts.motion import Outcome
from qnav.sim.config import WorldConfig
from qnav.sim.geometry import wall_segments
from qnav.sim.world import Observation, Transition, WorldState, observe, reset, step

if TYPE_CHECKING:
    from matplotlib.artist import Artist
    from matplotlib.axes import Axes
    from matplotlib.collections import LineCollection
    from matplotlib.figure import Figure
    from matplotlib.lines import Line2D
    from matplotlib.patches import Circle
    from matplotlib.text import Text
    from PIL.Image import Image

    from qnav.sim.evaluate import Agent

F64 = NDArray[np.float64]

_VIZ_MISSING = "rendering needs matplotlib and pillow: pip install 'qnav[viz]'"

TRAIL_STEPS = 25
"""Past obstacle positions drawn behind each obstacle: 5 s at the paper's 0.2 s period, long
enough to show where an obstacle came from without covering the arena in lines."""

RAY_STRIDE = 4
"""Draw every 4th lidar beam: 180 of the paper's 720 still show the scan's shape legibly."""

PNG_DPI = 100
"""Resolution of the still picture."""

GIF_DPI = 72
"""Resolution of the animation, lower than the PNG's to keep hundreds of frames small and fast."""

_FIGSIZE_IN = (8.0, 6.0)
"""Figure size; the right quarter holds the legend so it never hides part of the arena."""

_WALL_COLOUR = "#2b2b2b"
_PATH_COLOUR = "tab:blue"
_TARGET_COLOUR = "tab:green"
_RAY_COLOUR = "tab:red"


@dataclass(frozen=True)
class EpisodeRecord:
    """Everything needed to draw one episode, recorded step by step from a single world.

    Index t of the per-step arrays is the state after t actions, so index 0 is the start and
    index T (= len(actions)) is the state the episode ended in.
    """

    config: WorldConfig
    """The scenario the episode ran in (with the step limit it was recorded under)."""
    poses: F64
    """(T + 1, 3) robot x, y in metres and heading in radians."""
    obstacle_xy: F64
    """(T + 1, M, 2) obstacle centres in metres (M may be 0)."""
    target_xy: F64
    """(2,) target position in metres; it does not move during an episode."""
    scans: NDArray[np.float32] | None
    """(T + 1, B) lidar ranges in metres, +inf for no return; None for a lidar-less scenario."""
    actions: NDArray[np.int64]
    """(T,) action taken at each step."""
    outcome: Outcome
    """Outcome of the last step: SUCCESS, COLLISION, or RUNNING when the step limit cut it off."""
    rewards: F64
    """(T,) reward of each step."""

    @property
    def steps(self) -> int:
        """Number of steps taken (T)."""
        return int(self.actions.shape[0])

    @property
    def outcome_label(self) -> str:
        """How the episode ended, in the words of the paper's tables."""
        return {
            Outcome.SUCCESS: "success",
            Outcome.COLLISION: "collision",
            Outcome.RUNNING: "unfinished",
        }[self.outcome]


class EpisodeRecorder:
    """Keeps every state of one world's episode (index 0 of a batch of one) as it runs."""

    def __init__(self, state: WorldState, observation: Observation) -> None:
        self.target_xy = np.array(state.target_xy[0], dtype=np.float64)
        self.poses: list[F64] = []
        self.obstacles: list[F64] = []
        self.scans: list[NDArray[np.float32]] = []
        self.actions: list[int] = []
        self.rewards: list[float] = []
        self.outcome = Outcome.RUNNING
        self._keep(state, observation)

    def add(
        self, state: WorldState, observation: Observation, transition: Transition, action: int
    ) -> None:
        """Keep the state one step led to."""
        self._keep(state, observation)
        self.actions.append(action)
        self.rewards.append(float(transition.reward[0]))
        self.outcome = Outcome(int(transition.outcome[0]))

    def _keep(self, state: WorldState, observation: Observation) -> None:
        self.poses.append(state.pose[0].copy())
        self.obstacles.append(state.obstacle_xy[0].copy())
        if observation.scan_m is not None:
            self.scans.append(observation.scan_m[0].copy())

    def record(self, config: WorldConfig) -> EpisodeRecord:
        """The episode so far."""
        return EpisodeRecord(
            config=config,
            poses=np.array(self.poses, dtype=np.float64),
            obstacle_xy=np.array(self.obstacles, dtype=np.float64).reshape(len(self.poses), -1, 2),
            target_xy=self.target_xy,
            scans=None if config.lidar is None else np.array(self.scans, dtype=np.float32),
            actions=np.array(self.actions, dtype=np.int64),
            outcome=self.outcome,
            rewards=np.array(self.rewards, dtype=np.float64),
        )


def record_episode(
    config: WorldConfig,
    agent: Agent,
    seed: int,
    episode: int = 0,
    max_steps: int | None = None,
) -> EpisodeRecord:
    """Run episode `episode` of world seed `seed` to its end and keep every intermediate state.

    The layout is that of (seed, episode), the same one `evaluate` and `BatchedWorld` give that
    pair, so a picture can be matched with a line of an evaluation. The agent must accept a batch
    of one world (index 0).
    """
    if max_steps is not None:
        config = replace(config, max_episode_steps=max_steps)
    state = reset(config, np.array([seed], dtype=np.int64), np.array([episode], dtype=np.int64))
    observation = observe(config, state)
    agent.start(np.array([0], dtype=np.intp), np.array([episode], dtype=np.int64))
    recorder = EpisodeRecorder(state, observation)
    while True:
        action = np.asarray(agent.act(observation), dtype=np.int64).reshape(1)
        state, observation, transition = step(config, state, action)
        recorder.add(state, observation, transition, int(action[0]))
        if transition.terminated[0] or transition.truncated[0]:
            return recorder.record(config)


def draw_png(record: EpisodeRecord, path: Path, rays: bool = False) -> Path:
    """Draw the whole episode as it stood at its last step and write it as a PNG."""
    _require_viz()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scene = _Scene(record, rays=rays, dpi=PNG_DPI)
    scene.show(record.steps)
    scene.figure.savefig(path, dpi=PNG_DPI)
    return path


def draw_gif(
    record: EpisodeRecord, path: Path, rays: bool = False, fps: int = 10, stride: int = 1
) -> Path:
    """Animate the episode: one frame every `stride` steps, always ending on the last step.

    One figure is reused and only the moving artists are updated between frames, which keeps a
    200-step episode to a few seconds. Every frame is mapped onto one palette taken from the last
    frame (which holds the most colours: trails, the full path, rays), so colours do not flicker
    as they would with a palette per frame.
    """
    _require_viz()
    from PIL import Image as PILImage

    if fps < 1:
        raise ValueError(f"fps = {fps} is out of range: allowed [1, inf)")
    if stride < 1:
        raise ValueError(f"stride = {stride} is out of range: allowed [1, inf)")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    scene = _Scene(record, rays=rays, dpi=GIF_DPI)
    frame_steps = list(range(0, record.steps + 1, stride))
    if frame_steps[-1] != record.steps:
        frame_steps.append(record.steps)
    palette = scene.frame(record.steps).quantize(
        colors=256, method=PILImage.Quantize.MEDIANCUT, dither=PILImage.Dither.NONE
    )
    frames = [
        scene.frame(t).quantize(palette=palette, dither=PILImage.Dither.NONE) for t in frame_steps
    ]
    # Pillow takes milliseconds but GIF stores hundredths of a second: rates above 50 fps are lost.
    frames[0].save(
        path,
        format="GIF",
        save_all=True,
        append_images=frames[1:],
        duration=round(1000 / fps),
        loop=0,
        optimize=False,
    )
    return path


def render_episode(
    config: WorldConfig,
    agent: Agent,
    out_dir: Path,
    seed: int,
    episode: int = 0,
    *,
    rays: bool = False,
    max_steps: int | None = None,
) -> tuple[Path, Path]:
    """Record one episode and write `<scenario>-seed<seed>-ep<episode>` as a PNG and a GIF."""
    _require_viz()
    record = record_episode(config, agent, seed, episode, max_steps)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    stem = f"{config.name}-seed{seed}-ep{episode}"
    png = draw_png(record, out_dir / f"{stem}.png", rays=rays)
    gif = draw_gif(record, out_dir / f"{stem}.gif", rays=rays)
    return png, gif


class EpisodeCanvas:
    """Pictures of an episode still under way, one per call (gymnasium's `render`).

    The figure is laid out once per episode (`restart`), and each call draws the last step of the
    record it is given by blitting, so a picture every step costs milliseconds, not a new figure.
    """

    def __init__(self, rays: bool = True, dpi: int = GIF_DPI) -> None:
        _require_viz()
        self.rays = rays
        self.dpi = dpi
        self._scene: _Scene | None = None

    def restart(self) -> None:
        """The next record drawn is of a new episode."""
        self._scene = None

    def draw(self, record: EpisodeRecord) -> NDArray[np.uint8]:
        """The picture (H, W, 3) of the record's last step; the record extends the one before
        it since `restart` (same start, target and obstacles)."""
        if self._scene is None:
            self._scene = _Scene(record, rays=self.rays, dpi=self.dpi)
        else:
            self._scene.record = record
        return np.asarray(self._scene.frame(record.steps), dtype=np.uint8)


def _require_viz() -> None:
    """Fail early with the install hint, before any work is done, when plotting is missing."""
    try:
        import matplotlib  # noqa: F401 - optional extra, imported on use
        import PIL  # noqa: F401
    except ImportError as error:  # named, so `qnav` reports the extra as for any verb
        raise ModuleNotFoundError(_VIZ_MISSING, name=error.name or "matplotlib") from error


class _Scene:
    """One figure of an episode whose moving parts can be set to any step.

    Static parts (walls, target, start, legend) are drawn once; `show(t)` only moves artists.
    The figure uses the Agg canvas directly, without pyplot, so no window or global backend is
    involved and nothing leaks between figures.
    """

    def __init__(self, record: EpisodeRecord, rays: bool, dpi: int) -> None:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure

        self.record = record
        config = record.config
        self.rays = rays and record.scans is not None and config.lidar is not None

        self.figure: Figure = Figure(figsize=_FIGSIZE_IN, dpi=dpi)
        self.canvas = FigureCanvasAgg(self.figure)
        self.figure.subplots_adjust(left=0.08, right=0.72, bottom=0.09, top=0.92)
        ax: Axes = self.figure.add_subplot()
        self.axes = ax
        margin_m = max(0.6, 1.2 * config.robot_radius_m)
        ax.set_xlim(-margin_m, config.arena.size_m + margin_m)
        ax.set_ylim(-margin_m, config.arena.size_m + margin_m)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.grid(True, color="0.92", linewidth=0.6, zorder=0)
        ax.set_axisbelow(True)

        handles: list[Any] = []
        self._draw_walls(handles)
        self._draw_rays(handles)  # first, so they pass under everything else
        self._draw_obstacles(handles)
        self._draw_target_and_start(handles)
        self._draw_robot(handles)
        ax.legend(
            handles=handles,
            loc="upper left",
            bbox_to_anchor=(1.02, 1.0),
            borderaxespad=0.0,
            fontsize="small",
            frameon=False,
        )
        self.title: Text = ax.set_title("")
        # Everything drawn in the arena, for blitting; z-order decides what lies on top.
        self._data_artists: list[Artist] = sorted(
            [*ax.collections, *ax.patches, *ax.lines], key=lambda artist: artist.get_zorder()
        )
        self._background: Any = None

    def _draw_walls(self, handles: list[Any]) -> None:
        """The arena's walls, and their legend entry."""
        from matplotlib.collections import LineCollection
        from matplotlib.lines import Line2D

        segments = wall_segments(self.record.config.arena)
        walls = np.stack([segments.start, segments.end], axis=1)
        self.axes.add_collection(
            LineCollection(
                list(walls), colors=_WALL_COLOUR, linewidths=4.0, capstyle="butt", zorder=3
            )
        )
        handles.append(Line2D([], [], color=_WALL_COLOUR, linewidth=4.0, label="wall"))

    def _draw_rays(self, handles: list[Any]) -> None:
        """The lidar's rays (hits and misses, set by `show`), where they are drawn."""
        from matplotlib.collections import LineCollection
        from matplotlib.colors import to_rgba
        from matplotlib.lines import Line2D

        self.ray_hits: LineCollection = LineCollection(
            [], colors=[to_rgba(_RAY_COLOUR, 0.35)], linewidths=0.6, zorder=1
        )
        self.ray_misses: LineCollection = LineCollection(
            [], colors=[to_rgba(_RAY_COLOUR, 0.1)], linewidths=0.6, linestyles="dotted", zorder=1
        )
        if self.rays:
            self.axes.add_collection(self.ray_hits)
            self.axes.add_collection(self.ray_misses)
            handles.append(
                Line2D([], [], color=_RAY_COLOUR, alpha=0.5, linewidth=0.8, label="lidar rays")
            )

    def _draw_obstacles(self, handles: list[Any]) -> None:
        """One circle per moving obstacle, each in its own colour, and their trails."""
        from matplotlib.collections import LineCollection
        from matplotlib.colors import to_rgba
        from matplotlib.patches import Circle

        num_obstacles = self.record.obstacle_xy.shape[1]
        cycle = [f"C{i}" for i in range(1, 10) if i != 2]  # C0 is the path, C2 the target
        self.obstacle_rgba = np.array(
            [to_rgba(cycle[i % len(cycle)]) for i in range(num_obstacles)], dtype=np.float64
        ).reshape(num_obstacles, 4)
        self.trails: LineCollection = LineCollection([], linewidths=1.5, zorder=2)
        self.axes.add_collection(self.trails)
        self.obstacles: list[Circle] = []
        obstacle_radius_m = self.record.config.obstacles.radius_m
        for rgba in self.obstacle_rgba:
            circle = Circle(
                (0.0, 0.0),
                obstacle_radius_m,
                facecolor=(*rgba[:3], 0.35),
                edgecolor=tuple(rgba),
                linewidth=1.2,
                zorder=4,
            )
            self.axes.add_patch(circle)
            self.obstacles.append(circle)
        if num_obstacles:
            handles.append(
                Circle(
                    (0.0, 0.0),
                    obstacle_radius_m,
                    facecolor=(0.5, 0.5, 0.5, 0.35),
                    edgecolor="0.4",
                    label="obstacle (+ trail)",
                )
            )

    def _draw_target_and_start(self, handles: list[Any]) -> None:
        """The target with its reach radius, and the start with its heading."""
        from matplotlib.patches import Circle

        ax, record = self.axes, self.record
        radius_m = record.config.robot_radius_m
        target = record.target_xy
        ax.add_patch(
            Circle(
                (float(target[0]), float(target[1])),
                radius_m,
                fill=False,
                edgecolor=_TARGET_COLOUR,
                linestyle="--",
                linewidth=1.2,
                zorder=3,
            )
        )
        (target_marker,) = ax.plot(
            [target[0]],
            [target[1]],
            marker="*",
            markersize=16,
            color=_TARGET_COLOUR,
            markeredgecolor="darkgreen",
            linestyle="none",
            zorder=6,
            label="target (reach radius)",
        )
        handles.append(target_marker)
        start = record.poses[0]
        (start_marker,) = ax.plot(
            [start[0]],
            [start[1]],
            marker="s",
            markersize=7,
            markerfacecolor="white",
            markeredgecolor=_PATH_COLOUR,
            linestyle="none",
            zorder=6,
            label="start",
        )
        handles.append(start_marker)
        ax.plot(
            [start[0], start[0] + radius_m * math.cos(start[2])],
            [start[1], start[1] + radius_m * math.sin(start[2])],
            color=_PATH_COLOUR,
            linewidth=1.0,
            alpha=0.6,
            zorder=5,
        )

    def _draw_robot(self, handles: list[Any]) -> None:
        """The robot's path, body and heading (placed by `show`)."""
        from matplotlib.colors import to_rgba
        from matplotlib.patches import Circle

        ax = self.axes
        (self.path,) = ax.plot(
            [], [], color=_PATH_COLOUR, linewidth=1.6, zorder=5, label="robot path"
        )
        handles.append(self.path)
        self.robot: Circle = Circle(
            (0.0, 0.0),
            self.record.config.robot_radius_m,
            facecolor=(*to_rgba(_PATH_COLOUR)[:3], 0.25),
            edgecolor=_PATH_COLOUR,
            linewidth=1.5,
            zorder=7,
            label="robot (heading)",
        )
        ax.add_patch(self.robot)
        handles.append(self.robot)
        self.heading: Line2D = ax.plot([], [], color="navy", linewidth=2.0, zorder=8)[0]

    def show(self, t: int) -> None:
        """Move every moving artist to where it was after step t."""
        record = self.record
        config = record.config
        x_m, y_m, heading_rad = (float(v) for v in record.poses[t])
        radius_m = config.robot_radius_m

        self.path.set_data(record.poses[: t + 1, 0], record.poses[: t + 1, 1])
        self.robot.set_center((x_m, y_m))
        self.heading.set_data(
            [x_m, x_m + radius_m * math.cos(heading_rad)],
            [y_m, y_m + radius_m * math.sin(heading_rad)],
        )

        for circle, xy in zip(self.obstacles, record.obstacle_xy[t], strict=True):
            circle.set_center((float(xy[0]), float(xy[1])))
        self._show_trails(t)
        if self.rays:
            self._show_rays(t)

        # A record of an episode still under way (gymnasium's render) ends neither at the target,
        # in a collision nor at the step limit: its last step is "running", not "unfinished".
        ended = record.outcome != Outcome.RUNNING or record.steps >= config.max_episode_steps
        label = record.outcome_label if t == record.steps and ended else "running"
        self.title.set_text(f"{config.name}: {label}, step {t} of {record.steps}")

    def _show_trails(self, t: int) -> None:
        """Segments between each obstacle's last `TRAIL_STEPS` positions, fading with age."""
        first = max(0, t - TRAIL_STEPS)
        history = self.record.obstacle_xy[first : t + 1]  # (K, M, 2)
        num_segments, num_obstacles = history.shape[0] - 1, history.shape[1]
        if num_segments < 1 or num_obstacles == 0:
            self.trails.set_segments([])
            return
        # (K - 1, M, 2, 2) -> obstacle-major (M * (K - 1), 2, 2).
        pairs = np.stack([history[:-1], history[1:]], axis=2).transpose(1, 0, 2, 3)
        # Age of each segment: 1 for the oldest a full trail keeps, towards 0 for the newest.
        age = (t - (first + np.arange(num_segments))) / TRAIL_STEPS
        alpha = 0.7 * (1.0 - age) + 0.05
        colours = np.repeat(self.obstacle_rgba[:, None, :], num_segments, axis=1)
        colours[..., 3] = alpha[None, :]
        self.trails.set_segments(list(pairs.reshape(-1, 2, 2)))
        rgba: list[tuple[float, float, float, float]] = [
            (r, g, b, a) for r, g, b, a in colours.reshape(-1, 4).tolist()
        ]
        self.trails.set_color(rgba)

    def _show_rays(self, t: int) -> None:
        """Every `RAY_STRIDE`-th beam of the scan at step t; beams without a return faintly."""
        record = self.record
        lidar = record.config.lidar
        assert record.scans is not None and lidar is not None  # guaranteed by self.rays
        origin = record.poses[t, :2]
        angles_rad = record.poses[t, 2] + lidar.beam_angles_rad()[::RAY_STRIDE]
        ranges_m = record.scans[t, ::RAY_STRIDE].astype(np.float64)
        hit = np.isfinite(ranges_m)
        length_m = np.where(hit, ranges_m, lidar.max_range_m)
        direction = np.stack([np.cos(angles_rad), np.sin(angles_rad)], axis=1)
        ends = origin + length_m[:, None] * direction
        starts = np.broadcast_to(origin, ends.shape)
        rays = np.stack([starts, ends], axis=1)  # (R, 2, 2)
        self.ray_hits.set_segments(list(rays[hit]))
        self.ray_misses.set_segments(list(rays[~hit]))

    def frame(self, t: int) -> Image:
        """The picture after step t as an RGB image, drawn by blitting.

        A full redraw lays out ticks, labels and the legend again at every frame, which costs
        most of the time. Instead the first call renders the figure without the data artists
        and keeps that background; each frame restores it and draws only the data artists, in
        z-order, and the title, which gives the same picture several times faster.
        """
        from PIL import Image as PILImage

        canvas = self.canvas
        if self._background is None:
            for artist in self._data_artists:
                artist.set_animated(True)
            self.title.set_animated(True)
            canvas.draw()  # type: ignore[no-untyped-call]
            self._background = canvas.copy_from_bbox(self.figure.bbox)  # type: ignore[no-untyped-call]
        self.show(t)
        canvas.restore_region(self._background)  # type: ignore[no-untyped-call]
        for artist in self._data_artists:
            self.axes.draw_artist(artist)
        self.figure.draw_artist(self.title)
        rgba = np.asarray(canvas.buffer_rgba())  # type: ignore[no-untyped-call]
        return PILImage.fromarray(np.ascontiguousarray(rgba[..., :3]))
