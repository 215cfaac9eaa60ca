"""Render one sample of every synthetic action for a visual check.

    python tools/render_actions.py --out renders/actions [--gif] [--seed 0] [--version 2]

For each action (and one "walk while waving" pair) writes `<action>.png`: film strips
of eight key frames from the side and from the front and a top view of the root and
feet paths, from the stored joints (`features_to_joints(joints_to_features(...))`,
exactly what the corpus stores); with --gif also `<action>.gif` via `segmo.render`.
`--only` names the actions to render; a name that is none of them is refused in one line
(exit status 2) that lists the known ones.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from segmo.cli import run
from segmo.errors import ArgumentParser, non_negative_int
from segmo.motion.features import features_to_joints, joints_to_features
from segmo.motion.skeleton import T2M
from segmo.synth.actions import ACTIONS, sample_params
from segmo.synth.sequence import VERSION, VERSIONS, motion_from_actions

# Preview parameters that make each action easy to recognise (sampled otherwise).
PREVIEW = {"turn": {"direction": "left", "angle": 90}, "wave": {"hand": "right", "count": 3}}
OVERLAY = "walk_forward+wave"  # the one action with another on top


def contact_sheet(joints: np.ndarray, title: str, path: Path, frames: int = 8) -> None:
    """joints: (t, 22, 3) y up. Film strips of key frames seen from the side (z, y) and
    from the front (x, y), each pose centred on its root; and a top view of the paths."""
    fig = Figure(figsize=(16, 7), dpi=70)
    fig.suptitle(title, fontsize=11)
    t = len(joints)
    keys = np.linspace(0, t - 1, frames).round().astype(int)
    grid = fig.add_gridspec(2, 4)
    views = [("side view (+z = forward, to the right)", 2, 1), ("front view (+x = body's left, to the right)", 0, 1)]
    for k, (name, h, v) in enumerate(views):
        ax = fig.add_subplot(grid[k, :3])
        for n, i in enumerate(keys):
            shift = 1.3 * n - joints[i, 0, h]
            for c, p in enumerate(T2M.parents):
                if p < 0:
                    continue
                side = T2M.joint_names[c].split("_")[0]
                colour = {"left": "tab:blue", "right": "tab:red"}.get(side, "tab:green")
                ax.plot(joints[i, [p, c], h] + shift, joints[i, [p, c], v], color=colour, lw=1.8)
            ax.text(1.3 * n, -0.15, f"{i}", ha="center", fontsize=8)
        ax.axhline(0, color="grey", lw=0.5)
        ax.set_aspect("equal")
        ax.set_ylim(-0.25, 2.0)
        ax.set_title(name, fontsize=9)
    ax = fig.add_subplot(grid[:, 3])
    ax.plot(joints[:, 0, 0], joints[:, 0, 2], "g-", label="root")
    ax.plot(joints[:, 10, 0], joints[:, 10, 2], "b.", ms=2, label="left toe")
    ax.plot(joints[:, 11, 0], joints[:, 11, 2], "r.", ms=2, label="right toe")
    ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("x (left)")
    ax.set_ylabel("z (forward)")
    ax.legend(fontsize=7)
    ax.set_title(f"top view, {t} frames", fontsize=9)
    fig.savefig(path)


def main(argv: list[str] | None = None) -> None:
    parser = ArgumentParser(prog="render_actions.py", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("renders/actions"))
    parser.add_argument("--seed", type=non_negative_int, default=0)
    parser.add_argument("--gif", action="store_true", help="also write GIFs (slower)")
    parser.add_argument("--only", nargs="*", help="action names to render")
    parser.add_argument("--version", type=int, choices=VERSIONS, default=VERSION,
                        help="sample the parameters (durations) as this corpus version does (4: its rig too)")
    args = parser.parse_args(argv)
    known = [*ACTIONS, OVERLAY]
    unknown = [name for name in args.only or () if name not in known]
    if unknown:
        parser.error(f"--only {unknown[0]}: no such action; known: {', '.join(known)}")
    args.out.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(args.seed)
    jobs = []
    for name, spec in ACTIONS.items():
        params = sample_params(name, rng, args.version) | PREVIEW.get(name, {})
        plan = [("sit_down", {"duration": 2.0}), (name, params)] if spec.needs == "sitting" else [(name, params)]
        jobs.append((name, plan, None))
    jobs.append((OVERLAY, [("walk_forward", {"speed": 1.3, "steps": 8})],
                 ("wave", {"hand": "right"})))
    for name, plan, overlay in jobs:
        if args.only and name not in args.only:
            continue
        motion = motion_from_actions(rng, plan, overlay=overlay, rigid=args.version >= 4)
        joints = features_to_joints(joints_to_features(motion.joints.astype(np.float32)))
        title = " -> ".join(f"{a} {p}" for a, p in plan) + (f" + {overlay}" if overlay else "")
        contact_sheet(joints, title, args.out / f"{name}.png")
        if args.gif:
            from segmo.render import save_animation

            save_animation(joints, args.out / f"{name}.gif", title=title, stride=2)
        print(f"{name}: {len(joints)} frames")


if __name__ == "__main__":
    run("render_actions.py", main, sys.argv[1:])
