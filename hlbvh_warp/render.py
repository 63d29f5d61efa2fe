"""Tiny offline renderer for the examples: primary rays cast with `hlbvh_warp.intersect`,
Lambert shading against one directional light, PNG frames and an animated GIF."""

from __future__ import annotations

import pathlib

import numpy as np

from .query import intersect
from .reference import FLOAT32_MAX

#: From the box's centre towards the camera, before a `VIEWS` turn: above the mesh and mostly on
#: its +z side, a little to +x.
FRONT = (1.0, 0.55, 1.6)
#: Towards the directional light, before a `VIEWS` turn: above and behind the camera's left
#: shoulder, so the side seen is lit.
LIGHT = (0.4, 1.0, 0.6)
#: The side of the mesh the camera looks from, as a turn in degrees about the y axis (up) of both
#: `FRONT` and `LIGHT`: "front" the +z side, "right" +x, "back" -z, "left" -x. The rule is the
#: common convention that a model stands y up facing +z (the Stanford bunny, Blender's Suzanne
#: exported y up); a mesh that faces another way (the Stanford armadillo scan faces -z) needs its
#: side named. No automatic choice: a closed mesh's area-weighted normals sum to zero (they say
#: nothing), and the side showing more of the surface was the armadillo's back.
VIEWS = {"front": 0.0, "right": 90.0, "back": 180.0, "left": -90.0}


def turn_about_y(vector, degrees: float) -> np.ndarray:
    """``vector`` turned by ``degrees`` about the y axis (right-handed: +z turns towards +x)."""
    x, y, z = np.asarray(vector, dtype=np.float64)
    # Exact at the four quarter turns: "front" keeps FRONT and LIGHT bit for bit.
    c, s = {0.0: (1.0, 0.0), 90.0: (0.0, 1.0), 180.0: (-1.0, 0.0), -90.0: (0.0, -1.0)}.get(
        float(degrees), (np.cos(np.radians(degrees)), np.sin(np.radians(degrees))))
    return np.array([c * x + s * z, y, -s * x + c * z])


class Camera:
    """A pinhole camera looking at the centre of a box from a fixed direction, and the light that
    goes with it: ``view`` (a `VIEWS` name) turns both about the y axis, so that every side is lit
    as the front is."""

    def __init__(self, lower, upper, direction=FRONT, fov_degrees: float = 40.0, zoom: float = 1.0,
                 view: str = "front"):
        if view not in VIEWS:
            raise ValueError(f"unknown view {view!r}; choose from {', '.join(VIEWS)}")
        lower, upper = np.asarray(lower, dtype=np.float64), np.asarray(upper, dtype=np.float64)
        self.target = 0.5 * (lower + upper)
        radius = 0.5 * float(np.linalg.norm(upper - lower)) or 1.0
        back = turn_about_y(direction, VIEWS[view])
        back /= np.linalg.norm(back)
        self.light = turn_about_y(LIGHT, VIEWS[view])
        self.tan_half = np.tan(np.radians(fov_degrees) / 2.0)
        self.eye = self.target + back * (radius / np.sin(np.radians(fov_degrees) / 2.0)) / zoom
        # The rays start at the eye in float32, and a hit past float32's largest distance is a
        # miss: for a box larger than about 5e37 the eye was cast to Inf (with NumPy's overflow
        # warning), or the far part of the box lay out of reach, and the images were sky.
        reach = max(float(np.abs(self.eye).max()), float(np.linalg.norm(self.eye - self.target)) + radius)
        if not reach <= FLOAT32_MAX:
            raise ValueError(f"a box of diagonal {2.0 * radius:.3g} is too large to render: the camera framing it "
                             f"would reach {reach:.3g}, past float32's largest {FLOAT32_MAX:.3g}; scale the mesh "
                             f"down by a factor of {reach / FLOAT32_MAX:.3g} or more")
        self.forward = -back
        up = np.array([0.0, 1.0, 0.0]) if abs(back[1]) < 0.95 else np.array([0.0, 0.0, 1.0])
        self.right = np.cross(self.forward, up)
        self.right /= np.linalg.norm(self.right)
        self.up = np.cross(self.right, self.forward)

    @classmethod
    def framing(cls, vertices, **kwargs) -> "Camera":
        """A camera framing the bounding box of `vertices` (any shape reshaping to ``(V, 3)``)."""
        v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
        return cls(v.min(axis=0), v.max(axis=0), **kwargs)

    def rays(self, width: int, height: int):
        """One ray through the centre of every pixel, row-major from the top-left."""
        xs = (np.arange(width) + 0.5) / width * 2.0 - 1.0
        ys = 1.0 - (np.arange(height) + 0.5) / height * 2.0
        px, py = np.meshgrid(xs * self.tan_half * width / height, ys * self.tan_half)
        d = self.forward + px[..., None] * self.right + py[..., None] * self.up
        d /= np.linalg.norm(d, axis=-1, keepdims=True)
        o = np.broadcast_to(self.eye, d.shape)
        return o.reshape(-1, 3).astype(np.float32), d.reshape(-1, 3).astype(np.float32)


#: The mesh's colour, lit fully.
COLOR = (0.85, 0.72, 0.5)


def shade(vertices, faces, prim, directions, width: int, height: int, light=LIGHT) -> np.ndarray:
    """An ``(height, width, 3)`` uint8 image: two-sided Lambert plus ambient, the light coming
    from ``light``; misses get a sky."""
    v = np.asarray(vertices, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    light = np.asarray(light, dtype=np.float64)
    light /= np.linalg.norm(light)
    hit = prim >= 0
    image = np.empty((prim.shape[0], 3))
    sky = np.linspace(0.95, 0.7, height)[:, None].repeat(width, axis=1).reshape(-1)
    image[:] = sky[:, None] * np.array([0.75, 0.85, 1.0])
    tri = f[prim[hit]]
    n = np.cross(v[tri[:, 1]] - v[tri[:, 0]], v[tri[:, 2]] - v[tri[:, 0]])
    # Divided by its own length, whatever the scale: float64 holds the cross product of float32
    # edges (1e-90 to 1e78). A floor of 1e-30 shrank the normals of a mesh of size 1e-20 to
    # nearly zero and left it unlit; only a zero-area triangle (length 0) keeps n = 0.
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n /= np.where(length > 0.0, length, 1.0)
    # Face the normal towards the viewer, then light it.
    n *= -np.sign(np.einsum("ij,ij->i", n, directions[hit]))[:, None]
    lambert = np.clip(n @ light, 0.0, 1.0)
    image[hit] = (0.18 + 0.82 * lambert)[:, None] * np.asarray(COLOR)
    return (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(height, width, 3)


def render(bvh, camera: Camera, width: int = 256, height: int = 256) -> np.ndarray:
    """Ray-cast one frame of a BVH built over a mesh, lit by the camera's light; returns an
    ``(height, width, 3)`` uint8 image."""
    origins, directions = camera.rays(width, height)
    _, prim = intersect(bvh, origins, directions)
    return shade(bvh.vertices.numpy(), bvh.faces.numpy(), prim, directions, width, height, camera.light)


def save_png(image: np.ndarray, path) -> pathlib.Path:
    """Write an ``(height, width, 3)`` uint8 image as a PNG, creating its folder; returns the path.
    Needs Pillow."""
    from PIL import Image

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path)
    return path


#: Milliseconds each frame of a GIF shows: 12.5 frames a second.
MS_PER_FRAME = 80


def save_gif(images, path) -> pathlib.Path:
    """Write uint8 frames as a looping animated GIF of `MS_PER_FRAME` per frame, creating its
    folder; returns the path. Needs Pillow."""
    from PIL import Image

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    frames = [Image.fromarray(im) for im in images]
    frames[0].save(path, save_all=True, append_images=frames[1:], duration=MS_PER_FRAME, loop=0)
    return path


#: Dots per inch of the examples' matplotlib pictures (the collision and contact views).
FIGURE_DPI = 120


def legend_below(fig, ax) -> None:
    """A legend under the picture naming the colour of each of ``ax``'s scatters, with round markers
    of one size: the vertices' 0.2-point dots would not show in it."""
    import matplotlib.pyplot as plt

    handles = [plt.Line2D([], [], marker="o", linestyle="", markersize=6, color=c.get_facecolor()[0],
                          label=c.get_label()) for c in ax.collections]
    fig.legend(handles=handles, loc="lower center", ncol=1, fontsize=8, frameon=False)


def save_figure(fig, path) -> pathlib.Path:
    """Write a matplotlib figure as a PNG at `FIGURE_DPI`, creating its folder, and close it;
    returns the path."""
    import matplotlib.pyplot as plt

    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=FIGURE_DPI)
    plt.close(fig)
    return path
