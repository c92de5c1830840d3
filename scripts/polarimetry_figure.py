#!/usr/bin/env python3
"""Draw docs/images/polarimetry_frames.png: the beams and the s/p axes of pbrdf-cl's Stokes frames.

The frames are SPEC's (and the model's, ``reference.frame_rotations``): the mean surface's normal is
z; w_i points to the source (zenith theta_i, azimuth phi, so phi = 180 puts the source opposite the
viewer, in plane) and w_r to the viewer (zenith theta_r, azimuth 0); the beams propagate along
k_in = -w_i and k_out = w_r; each beam's s axis is unit(k x z) (perpendicular to its plane of
incidence on the mean surface), its p axis k x s.  A Stokes vector (S0, S1, S2, S3) is
S1 = |Es|^2 - |Ep|^2, S2 = 2 Re(Es Ep*), S3 = -2 Im(Es Ep*), in its beam's (s, p) axes; the AoP is
measured from s towards p.

    python scripts/polarimetry_figure.py [--phi 150] [--out docs/images/polarimetry_frames.png]
"""
import argparse

import numpy as np


def unit(v):
    return v / np.linalg.norm(v)


def frames(theta_i, theta_r, phi):
    """(w_i, w_r, (s_in, p_in), (s_out, p_out)) as SPEC defines them."""
    ti, tr, ph = np.radians([theta_i, theta_r, phi])
    w_i = np.array([np.sin(ti) * np.cos(ph), np.sin(ti) * np.sin(ph), np.cos(ti)])
    w_r = np.array([np.sin(tr), 0.0, np.cos(tr)])
    z = np.array([0.0, 0.0, 1.0])
    out = []
    for k in (-w_i, w_r):
        s = unit(np.cross(k, z))
        out.append((s, np.cross(k, s)))
    return w_i, w_r, out[0], out[1]


def draw(theta_i, theta_r, phi, path):
    from matplotlib.figure import Figure
    w_i, w_r, (s_in, p_in), (s_out, p_out) = frames(theta_i, theta_r, phi)
    fig = Figure(figsize=(7.2, 5.6))
    ax = fig.add_subplot(projection="3d")
    sq = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0], [-1, -1, 0]]) * 1.1
    ax.plot(sq[:, 0], sq[:, 1], sq[:, 2], color="0.6")
    ax.plot_trisurf([-1.1, 1.1, 1.1, -1.1], [-1.1, -1.1, 1.1, 1.1], [0, 0, 0, 0], color="0.9", alpha=0.5)
    ax.quiver(0, 0, 0, 0, 0, 0.8, color="0.3", arrow_length_ratio=0.12)
    ax.text(0, 0, 0.85, "z (normal)", color="0.3")
    src, eye = 1.6 * w_i, 1.6 * w_r
    ax.quiver(*src, *(-src), color="darkorange", arrow_length_ratio=0.08, linewidth=2)
    ax.quiver(0, 0, 0, *eye, color="purple", arrow_length_ratio=0.08, linewidth=2)
    ax.text(*(src * 1.05), "source: k_in = -w_i", color="darkorange")
    ax.text(*(eye * 1.02 - np.array([0.9, 0, 0])), "viewer: k_out = w_r", color="purple")
    for mid, s, p, tag in ((0.6 * src, s_in, p_in, "in"), (0.6 * eye, s_out, p_out, "out")):
        ax.quiver(*mid, *(0.6 * s), color="crimson", arrow_length_ratio=0.2)
        ax.quiver(*mid, *(0.6 * p), color="royalblue", arrow_length_ratio=0.2)
        ax.text(*(mid + 0.68 * s), f"s_{tag}", color="crimson")
        ax.text(*(mid + 0.68 * p), f"p_{tag}", color="royalblue")
    ax.set_xlim(-1.5, 1.5)
    ax.set_ylim(-1.5, 1.5)
    ax.set_zlim(0, 1.8)
    ax.set_xlabel("x (towards the viewer's azimuth)")
    ax.set_ylabel("y")
    ax.set_zlabel("z")
    ax.view_init(elev=20, azim=-115)
    ax.set_title(f"Stokes frames: theta_i {theta_i:g}, theta_r {theta_r:g}, phi {phi:g} deg (180 = in plane)\n"
                 "s = unit(k x z), p = k x s for each beam; AoP from s towards p", fontsize=9)
    fig.savefig(path, dpi=110, bbox_inches="tight")


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--theta-i", type=float, default=40.0)
    ap.add_argument("--theta-r", type=float, default=45.0)
    ap.add_argument("--phi", type=float, default=150.0)
    ap.add_argument("--out", default="docs/images/polarimetry_frames.png")
    a = ap.parse_args()
    draw(a.theta_i, a.theta_r, a.phi, a.out)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
