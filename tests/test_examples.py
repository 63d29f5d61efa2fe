"""Every example runs headless (and rendered, at a tiny size) for a few frames on every device."""

from __future__ import annotations

import importlib.util
import pathlib
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

EXAMPLES = pathlib.Path(__file__).resolve().parents[1] / "examples"


def load_example(name: str):
    spec = importlib.util.spec_from_file_location(name, EXAMPLES / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def red_pixels(fig, ax):
    """(column, row) pixel centres of the red of `fig`, drawn as a PNG at its own dpi and read
    back, inside ``ax`` and outside every legend; and the image's height."""
    import io

    from PIL import Image

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=fig.dpi)
    image = np.asarray(Image.open(buffer).convert("RGB")).astype(np.int64)
    height = image.shape[0]
    red = (image[..., 0] > 150) & (image[..., 0] - image[..., 1] > 80) & (image[..., 0] - image[..., 2] > 80)
    rows, cols = np.nonzero(red)
    x, y = cols + 0.5, height - rows - 0.5  # display coordinates: y up from the bottom

    def inside(box):
        return (x >= box.x0) & (x <= box.x1) & (y >= box.y0) & (y <= box.y1)

    keep = inside(ax.get_window_extent())
    for legend in fig.legends + [ax.get_legend()]:
        if legend is not None:
            keep &= ~inside(legend.get_window_extent())
    return np.stack([x[keep], y[keep]], axis=1)


def assert_red_on(fig, ax, points, tolerance=3.0, both_ways=True):
    """Every red pixel of the plot lies within ``tolerance`` pixels of one of ``points`` (data
    coordinates, drawn through ``ax``), and with ``both_ways`` every point has a red pixel that
    near: red marks those points and nothing else."""
    from scipy.spatial import cKDTree

    red = red_pixels(fig, ax)
    drawn = ax.transData.transform(np.asarray(points, dtype=np.float64))
    assert len(red) > 0 and len(drawn) > 0
    distance, _ = cKDTree(drawn).query(red)
    assert distance.max() <= tolerance, f"{(distance > tolerance).sum()} red pixels away from every point"
    if both_ways:
        distance, _ = cKDTree(red).query(drawn)
        assert distance.max() <= tolerance, f"{(distance > tolerance).sum()} points without red"


@pytest.mark.parametrize("headless", [True, False])
def test_exploding_mesh(device, headless, tmp_path):
    module = load_example("example_exploding_mesh")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=2000, image_size=24, headless=headless)
        for _ in range(3):
            example.step()
            example.render()
    rows = example.animation.rows
    assert [r["decision"] for r in rows] == ["rebuild"] * 3
    # Each frame's row says which order the resorted builder fed, as its report does.
    reports = list(example.animation.builder.reports)[-3:]
    table = example.animation.table().splitlines()
    for row, report, line in zip(rows, reports, table[1:]):
        expected = "resorted" if report["input_order"] == "previous tree" else "face order"
        assert row["input"].startswith(expected) and line.endswith(row["input"])
    if headless:
        assert example.save(tmp_path) == []
    else:
        paths = example.save(tmp_path)
        assert [p.suffix for p in paths] == [".png", ".gif"] and all(p.stat().st_size > 0 for p in paths)
        # The intact mesh, then the 3 frames.
        assert len(example.animation.images) == 4
        image = example.animation.images[-1]
        assert image.shape == (24, 24, 3) and image.dtype == np.uint8 and image.std() > 0


@pytest.mark.parametrize("view,turn", [("back", 2), ("right", 1), ("left", 3)])
def test_a_view_shows_the_mesh_as_the_front_shows_it_turned(view, turn):
    """A mesh seen from a side (`render.VIEWS`) is the mesh turned about y to bring that side to
    the front, seen from the front, pixel for pixel: the camera and its light turn together, so
    every side is lit as the front is (the armadillo scan, facing -z, showed its back, and a
    camera moved alone would have seen its front in its own shadow). Turned about the box's
    centre at the origin, by quarter turns, exactly."""
    import trimesh

    from hlbvh_warp import api, render

    # A mesh with no symmetry that a quarter turn maps onto itself, centred on the origin.
    mesh = trimesh.creation.annulus(r_min=0.2, r_max=0.5, height=0.3)
    mesh.vertices[:, 0] *= 1.7
    mesh.vertices[mesh.vertices[:, 2] > 0, 1] += 0.2
    vertices = np.asarray(mesh.vertices, dtype=np.float32)
    vertices -= np.float32(0.5) * (vertices.min(axis=0) + vertices.max(axis=0))
    faces = np.asarray(mesh.faces, dtype=np.int32)
    turned = vertices.copy()
    for _ in range(turn):
        # A quarter turn about y the other way, +x towards +z (the camera's side to the front):
        # (x, z) -> (-z, x), exact in float32.
        turned = np.stack([-turned[:, 2], turned[:, 1], turned[:, 0]], axis=1)
    side = render.render(api.build(vertices, faces), render.Camera.framing(vertices, view=view), 48, 48)
    front = render.render(api.build(turned, faces), render.Camera.framing(turned), 48, 48)
    assert (side != side[0, 0]).any(axis=-1).mean() > 0.1  # the mesh fills part of the picture
    assert np.abs(side.astype(int) - front).max() <= 1
    # The front is the camera and light every example had: no picture of the default changes.
    camera = render.Camera.framing(vertices)
    assert np.array_equal(camera.light, render.LIGHT)
    with pytest.raises(ValueError, match="unknown view 'top'; choose from front, right, back, left"):
        render.Camera.framing(vertices, view="top")


@pytest.mark.parametrize("scale", [2.0 ** -66, 2.0 ** -100, 2.0 ** 100])
def test_shading_does_not_depend_on_the_meshs_scale(scale):
    # The examples' and the demo's images light each hit by its triangle's normal, a direction:
    # scaling the mesh by a power of two (exact in every coordinate) must leave every pixel as it
    # was. The normal was divided by max(|n|, 1e-30), so on a mesh of size 1e-20 (|n| about
    # 1e-42) it came out near zero and 231 of 1024 pixels of a sphere lost their light.
    import trimesh

    from hlbvh_warp import render

    sphere = trimesh.creation.icosphere(2)
    vertices = np.asarray(sphere.vertices, np.float32)
    faces = np.asarray(sphere.faces, np.int32)
    _, directions = render.Camera.framing(vertices).rays(32, 32)
    # Every face, some more than once, lit from every side (the image need not be a true view).
    prim = np.arange(32 * 32) % len(faces)
    prim[::7] = -1
    unit = render.shade(vertices, faces, prim, directions, 32, 32)
    scaled = render.shade(vertices * np.float32(scale), faces, prim, directions, 32, 32)
    assert unit.std() > 0
    np.testing.assert_array_equal(scaled, unit)


def tetrahedron_ply(path, size: float):
    """A tetrahedron of ``size`` in every coordinate, written as an ASCII PLY."""
    corners = size * np.array([[-1, -1, -1], [1, -1, 1], [-1, 1, 1], [1, 1, -1]])
    path.write_text("ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
                    "property float z\nelement face 4\nproperty list uchar int vertex_indices\nend_header\n"
                    + "".join(f"{float(x)!r} {float(y)!r} {float(z)!r}\n" for x, y, z in corners)
                    + "3 0 1 2\n3 0 1 3\n3 0 2 3\n3 1 2 3\n")
    return path


def test_a_camera_past_float32s_reach_is_refused():
    # The examples' camera sits about 3 box diagonals out. For a box of 1e38 its eye was cast to
    # Inf (NumPy's overflow warning) and every ray missed; for the box of 5e37 below the eye fits,
    # but the box's far half lies more than float32's largest distance from it, where hits are
    # misses: part of the mesh, or all of it, rendered as sky.
    import trimesh

    from hlbvh_warp import api, query, render

    box = trimesh.creation.box(extents=(4.0, 2.0, 3.0))
    faces = np.asarray(box.faces, np.int32)
    limit = float(np.finfo(np.float32).max)
    for scale, zoom in ((5e37, 1.0), (1e38, 0.7)):
        vertices = np.asarray(box.vertices) * scale
        with pytest.raises(ValueError, match="too large to render.*past float32's largest"):
            render.Camera.framing(vertices, zoom=zoom)
    # The case: at 5e37 the eye is within range, and hits go missing.
    vertices = (np.asarray(box.vertices) * 5e37).astype(np.float32)
    small = (np.asarray(box.vertices) * 2.0 ** -100).astype(np.float32)
    camera, framed = render.Camera.__new__(render.Camera), render.Camera.framing(small)
    camera.__dict__.update(framed.__dict__, eye=framed.eye * 2.0 ** 100 * 5e37, target=framed.target * 5e37)
    assert np.abs(camera.eye).max() < limit
    counts = [int((query.intersect(api.build(v, faces, device="cpu"), *c.rays(24, 24))[1] >= 0).sum())
              for v, c in ((vertices, camera), (small, framed))]
    assert counts[0] < counts[1]
    # A box a little smaller renders.
    assert np.isfinite(render.Camera.framing(np.asarray(box.vertices) * 2e37).rays(4, 4)[0]).all()


@pytest.mark.parametrize("name", ["example_exploding_mesh", "example_bending_mesh", "example_camera_orbit"])
def test_rendering_examples_refuse_a_mesh_too_large_to_frame(name, tmp_path, capsys):
    # They wrote all-sky images, with no error, for a mesh larger than about 5e37.
    path = tetrahedron_ply(tmp_path / "huge.ply", 2e38)
    args = [*without_headless(TINY_ARGS[name]), "--out", str(tmp_path / "out")]
    err = argument_error(name, [*args, "--mesh", str(path)], capsys)
    assert "too large to render" in err and "Traceback" not in err, err
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["example_exploding_mesh", "example_bending_mesh"])
def test_headless_examples_make_no_camera(name, tmp_path):
    # Builds only: a mesh too large to frame is no reason to refuse them.
    from hlbvh_warp.cli import read_mesh

    module = load_example(name)
    example = module.Example(read_mesh(str(tetrahedron_ply(tmp_path / "huge.ply", 2e38))), headless=True)
    assert example.animation.camera is None


def test_bending_mesh(device, tmp_path):
    module = load_example("example_bending_mesh")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=2000, num_frames=24, image_size=16)
        for _ in range(4):
            example.step()
            example.render()
    rows = example.animation.rows
    assert all(r["sah_ratio"] <= 1.10 for r in rows), rows
    assert "refit" in {r["decision"] for r in rows}
    assert len(example.save(tmp_path)) == 2


def _border(image: np.ndarray) -> np.ndarray:
    return np.concatenate([image[0], image[-1], image[1:-1, 0], image[1:-1, -1]])


def test_bending_mesh_stays_in_the_picture_on_every_frame():
    # The camera framed the mesh at rest; bent, the mesh grew past that box, and from the third
    # of 6 frames on it was cut off at the image's edges. Every frame's border pixels, cast in
    # float64 against that frame's vertices, must miss the mesh, and the mesh must fill a fair
    # part of the picture (a camera far away would pass the first check with a speck).
    from oracles import brute_force_closest_hit

    module = load_example("example_bending_mesh")
    size, num_frames = 24, 6
    with wp.ScopedDevice("cpu"):
        example = module.Example(num_tris=2000, num_frames=num_frames, image_size=size, compare=False)
        animation = example.animation
        origins, directions = animation.camera.rays(size, size)
        for frame in range(num_frames + 1):
            if frame:
                example.step()
                example.render()
            vertices = animation.scene.vertices.numpy()
            _, prim = brute_force_closest_hit(vertices, animation.scene.faces, origins, directions)
            prim = prim.reshape(size, size)
            assert (_border(prim) < 0).all(), f"frame {frame}: the mesh touches the image's edge"
            assert (prim >= 0).mean() > 0.05, f"frame {frame}: the mesh covers {(prim >= 0).mean():.1%}"
    # The rest pose is the GIF's first frame: the bend is seen from its start.
    assert len(animation.images) == num_frames + 1


def test_refitting_builders_compile_the_refit_before_the_first_frame():
    # The examples time frames from the first: the refit's kernels, compiled at the first refit,
    # put their compilation (0.2-1.6 s on the CPU) into frame 1 of every table and plot of a
    # refitting policy, and the contact example's kernel its 6 s into frame 1's contact time. A
    # fresh process, so no earlier test has loaded the modules.
    code = """
import warp as wp
wp.config.quiet = True
from hlbvh_warp.builder import Builder
from hlbvh_warp.kernels.bounds import bounds_sweep_kernel
from hlbvh_warp.scenes import default_scene
v, f = default_scene(1000)
loaded = {}
for policy in ("rebuild", "refit", "auto"):
    bounds_sweep_kernel.module.unload()
    Builder(len(f), policy=policy, device="cpu").build(v, f)
    loaded[policy] = bool(bounds_sweep_kernel.module.execs)
import importlib.util
spec = importlib.util.spec_from_file_location("contact", "examples/example_mesh_contact.py")
contact = importlib.util.module_from_spec(spec)
spec.loader.exec_module(contact)
with wp.ScopedDevice("cpu"):
    contact.Example(num_tris=1000, num_particles=10, headless=True)
loaded["contact"] = bool(contact.contact_kernel.module.execs)
print(loaded)
"""
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True,
                         cwd=pathlib.Path(__file__).resolve().parents[1]).stdout
    assert out.strip().splitlines()[-1] == "{'rebuild': False, 'refit': True, 'auto': True, 'contact': True}", out


def test_frame_timing(device, tmp_path):
    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        modes = ["hlbvh scratch", "hlbvh auto", "hlbvh_sah scratch", "hlbvh_sah resorted", "wp.Bvh sah"]
        # One subdivision: the 1000-triangle scene becomes 4000 triangles (the paper-size option).
        example = module.Example(num_tris=1000, num_frames=3, modes=modes, headless=True,
                                 subdivide_times=1)
        scratch = next(iter(example.sequences.values()))["runners"]["hlbvh scratch"]
        assert scratch.num_prims == 4 * len(module.scene(None, 1000)[1])
        for _ in range(3):
            example.step()
            example.render()
    table = example.table()
    assert all(mode in table for mode in modes)
    # Resorting does not change the tree: the SAH of every resorted frame is the scratch build's.
    for seq in example.sequences.values():
        np.testing.assert_allclose(seq["sah"]["hlbvh_sah resorted"], seq["sah"]["hlbvh_sah scratch"], rtol=1e-5)
    for seq in example.sequences.values():
        assert all(len(ms) == 3 for ms in seq["ms"].values())
    path = example.plot(str(tmp_path / "timing.png"))
    assert pathlib.Path(path).stat().st_size > 0


def test_frame_timing_plot_reads_without_the_code(tmp_path, monkeypatch):
    """The figure the plot writes, read back as drawn: every panel's axes say what they measure
    and in which unit, each mode's line holds that mode's times, every builder has a colour of its
    own (its scratch, resorted and auto modes one line style each), and the legend, with every
    mode, covers no panel's data (it sat over the curves, in the middle of the panel)."""
    import matplotlib.figure

    module = load_example("example_frame_timing")
    modes = ["hlbvh scratch", "hlbvh resorted", "hlbvh auto", "lbvh scratch", "lbvh resorted", "wp.Bvh sah",
             "wp.Bvh lbvh"]
    with wp.ScopedDevice("cpu"):
        example = module.Example(num_tris=1000, num_frames=3, modes=modes, headless=True)
        for _ in range(3):
            example.step()
    figures = []
    original = matplotlib.figure.Figure.savefig

    def keep(fig, *args, **kwargs):
        figures.append(fig)
        return original(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    example.plot(str(tmp_path / "timing.png"))
    (fig,) = figures
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)  # pyplot detached the closed figure from its canvas
    canvas.draw()
    renderer = canvas.get_renderer()
    panels = [ax for ax in fig.axes if ax.lines]
    assert [ax.get_title().split(":")[0] for ax in panels] == list(example.sequences)
    legends = [ax.get_legend() for ax in fig.axes if ax.get_legend()] + fig.legends
    assert legends, "no legend"
    labels = {text.get_text() for legend in legends for text in legend.get_texts()}
    assert labels == set(modes)
    for ax, seq in zip(panels, example.sequences.values()):
        assert ax.get_xlabel() == "frame"
        assert "(ms)" in ax.get_ylabel() and "frame" in ax.get_ylabel()
        lines = {line.get_label(): line for line in ax.lines}
        for label, ms in seq["ms"].items():
            np.testing.assert_array_equal(lines[label].get_ydata(), ms)
            np.testing.assert_array_equal(lines[label].get_xdata(), np.arange(1, len(ms) + 1))
        colors = {label: matplotlib.colors.to_hex(line.get_color()) for label, line in lines.items()}
        styles = {label: line.get_linestyle() for label, line in lines.items()}
        builders = {label: label.split()[0] if not label.startswith("wp.Bvh") else label for label in lines}
        for a in lines:
            for b in lines:
                if a < b:
                    assert (colors[a] == colors[b]) == (builders[a] == builders[b]), (a, b, colors)
                    if builders[a] == builders[b]:
                        assert styles[a] != styles[b], (a, b)
        # Pixel boxes: the legend lies outside every panel.
        for legend in legends:
            box = legend.get_window_extent(renderer)
            for panel in panels:
                assert not box.overlaps(panel.get_window_extent(renderer)), "the legend covers a panel"


def test_frame_timing_table_without_references(device):
    """A run with no scratch or resorted mode of a method has no reference for its ratios: the
    cells say so ("-") instead of printing nan, while the measured columns are still numbers."""
    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=500, num_frames=1, sequences=("bend",), modes=["hlbvh auto"],
                                 headless=True)
        example.step()
    row = next(line for line in example.table().splitlines() if "hlbvh auto" in line)
    assert "nan" not in row.lower()
    cells = row.split()
    assert cells[6:8] == ["-", "-"], row  # sequence, two words of mode, three times, the ratios
    assert float(cells[3]) == pytest.approx(np.mean(example.sequences["bend"]["ms"]["hlbvh auto"]), abs=0.01)


def test_frame_timing_stage_table(device):
    """`--stages`: each Builder mode's line lists the mean of every stage its frames ran (a
    skipped stage counts 0), their total, and the part of it in the sort stages; the names the
    share adds up are stages the pipeline really reports, on both of its sort paths (a renamed
    stage would silently leave the share)."""
    from hlbvh_warp.builder import Builder
    from hlbvh_warp.config import BuildConfig

    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1000, num_frames=2, sequences=("static", "bend"),
                                 modes=["hlbvh scratch", "hlbvh resorted", "wp.Bvh sah"], headless=True, stages=True)
        for _ in range(2):
            example.step()
        reported = set()
        vertices, faces = module.scene(None, 1000)
        for runs in (0.0, 1.0):  # the global radix sort, and compress-sort-decompress
            builder = Builder(len(faces), BuildConfig(global_sort_runs=runs), resort=False, timings=True)
            builder.build(vertices, faces)
            report = builder.update(vertices[::-1].copy())  # a new order: every sort stage has work
            reported |= set(report["stages_ms"])
        resorting = Builder(len(faces), timings=True)
        resorting.build(vertices, faces)
        reported |= set(resorting.update(vertices)["stages_ms"])
    assert set(module.SORT_STAGES) <= reported, set(module.SORT_STAGES) - reported
    lines = example.stage_table().splitlines()
    assert not any("wp.Bvh" in line for line in lines)
    for name, seq in example.sequences.items():
        for label in ("hlbvh scratch", "hlbvh resorted"):
            line = next(x for x in lines if x.split()[:3] == [name, *label.split()])
            frames = seq["stages"][label]
            listed = dict(zip(line.split(": ", 1)[1].split()[::2], map(float, line.split(": ", 1)[1].split()[1::2])))
            assert set(listed) == set().union(*frames)
            for stage, ms in listed.items():
                assert ms == pytest.approx(np.mean([f.get(stage, 0.0) for f in frames]), abs=0.006), (stage, line)
            total = float(line.split("stages")[1].split()[0])
            sort = float(line.split("sort stages")[1].split()[0])
            assert total == pytest.approx(sum(listed.values()), abs=0.006 * len(listed))
            assert sort == pytest.approx(sum(v for k, v in listed.items() if k in module.SORT_STAGES),
                                         abs=0.006 * len(listed))


def test_frame_timing_static_sequence(device):
    """The "static" sequence rebuilds the mesh at rest every frame (the paper's resorting of an
    already sorted model): the vertices never move, and the resorted tree is the scratch one."""
    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1000, num_frames=2, sequences=("static",),
                                 modes=["hlbvh scratch", "hlbvh resorted"], headless=True)
        seq = example.sequences["static"]
        rest = seq["anim"].vertices.numpy().copy()
        for _ in range(2):
            example.step()
        np.testing.assert_array_equal(seq["anim"].vertices.numpy(), rest)
        resorted = seq["runners"]["hlbvh resorted"]
        # Fed the previous tree's order, which is this frame's sorted order.
        np.testing.assert_array_equal(resorted.input_order.numpy(), resorted.bvh.prim_order.numpy())
    np.testing.assert_allclose(seq["sah"]["hlbvh resorted"], seq["sah"]["hlbvh scratch"], rtol=1e-6)
    table = example.table()
    assert "static" in table
    # The sorted previous order is always taken, and the table counts those frames.
    resorted_row = next(line for line in table.splitlines() if "hlbvh resorted" in line)
    assert resorted_row.endswith("rebuild 2 (resorted 2)")
    # The table says what "(resorted N)" counts: the rebuilt frames fed the last tree's order, as
    # the Builder's reports say.
    assert "(resorted N): of the rebuilt frames, those fed the last frame's tree order" in table.splitlines()[-1]
    reports = list(resorted.reports)[-2:]
    assert [r["input_order"] for r in reports] == ["previous tree"] * 2


def test_scene_builds(device):
    """Several meshes moved and built every frame three ways; every tree is checked against
    the moved vertices (each leaf's box is its triangle's), not only timed."""
    module = load_example("example_scene_builds")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=(3000, 1500, 400), num_frames=2, headless=True)
        for _ in range(2):
            example.step()
            example.render()
    assert all(len(ms) == 2 for ms in example.ms.values())
    assert all(mode in example.table() for mode in module.MODES)
    for obj in example.objects:
        verts = obj["vertices"].numpy()[obj["faces_np"]]
        for bvh in (example.bvhs[id(obj)], obj["builder"].bvh, obj["plain"].bvh):
            arrays = bvh.to_numpy()
            leaves = np.flatnonzero(arrays["node_end"] - arrays["node_begin"] == 1)
            prims = arrays["prim_order"][arrays["node_begin"][leaves]]
            np.testing.assert_allclose(arrays["node_lowers"][leaves], verts[prims].min(axis=1), rtol=0, atol=1e-6)
            np.testing.assert_allclose(arrays["node_uppers"][leaves], verts[prims].max(axis=1), rtol=0, atol=1e-6)


def test_scene_builds_moves_the_meshes_every_timed_frame(device):
    """No timed frame rebuilds the vertices of the frame before it (the warm-up included)."""
    module = load_example("example_scene_builds")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=(1000, 400), num_frames=3, headless=True)
        previous = [obj["vertices"].numpy().copy() for obj in example.objects]
        for _ in range(3):
            example.step()
            current = [obj["vertices"].numpy().copy() for obj in example.objects]
            for before, after in zip(previous, current):
                assert not np.array_equal(before, after), f"frame {example.frame} did not move the meshes"
            previous = current


@pytest.mark.parametrize("headless", [True, False])
def test_particle_collisions(device, headless, tmp_path):
    """The broad phase through the per-frame box BVH finds exactly the touching sphere pairs a
    float64 all-pairs test finds, every frame, under each policy."""
    module = load_example("example_particle_collisions")
    for policy in ("rebuild", "auto"):
        with wp.ScopedDevice(device):
            # Big spheres in few numbers: many contacts, and the pair buffer has to grow.
            example = module.Example(num_particles=1500, policy=policy, headless=headless, radius=0.03,
                                     speed=0.05, peer=policy == "rebuild")
            for _ in range(3):
                row = example.step()
                example.render()
                c = example.centers.numpy().astype(np.float64)
                r = example.radii.numpy().astype(np.float64)
                d2 = ((c[:, None] - c[None]) ** 2).sum(-1)
                touch = np.triu(d2 < (r[:, None] + r[None]) ** 2, k=1)
                expected = np.argwhere(touch)
                assert len(expected) > 0
                np.testing.assert_array_equal(example.contact_pairs(), expected)
                assert row["contacts"] == len(expected)
        decisions = {row["decision"] for row in example.rows}
        assert decisions == {"rebuild"} if policy == "rebuild" else decisions <= {"rebuild", "refit", "none"}
        assert "average" in example.table()
    paths = example.save(tmp_path)
    assert len(paths) == (0 if headless else 1)


def test_particle_collisions_picture_says_what_it_shows():
    """The picture of the last frame: each particle of the slab at its centre's pixel, red where
    a float64 all-pairs test finds it touching another sphere and blue elsewhere; the title names
    the frame and the counts, the legend the two colours."""
    import matplotlib.pyplot as plt

    module = load_example("example_particle_collisions")
    example = module.Example(num_particles=800, radius=0.03, speed=0.05, peer=False)
    for _ in range(2):
        example.step()
    example.render()
    c = example.centers.numpy().astype(np.float64)
    r = example.radii.numpy().astype(np.float64)
    d2 = ((c[:, None] - c[None]) ** 2).sum(-1)
    touch = d2 < (r[:, None] + r[None]) ** 2
    np.fill_diagonal(touch, False)
    touching = touch.any(axis=1)
    slab = np.abs(c[:, 2] - 0.5) < module.SLAB_HALF_DEPTH
    size = example.image.shape[0]
    px = np.clip((c[:, :2].astype(np.float32) * size).astype(int), 0, size - 1)
    red = np.all(example.image == np.float32(module.CONTACT_COLOR), axis=-1)
    at = red[size - 1 - px[:, 1], px[:, 0]]
    # Every touching particle of the slab is red; a free one is red only where it shares its pixel
    # with a touching one.
    assert at[slab & touching].all() and (slab & touching).sum() > 0
    shared = {(x, y) for x, y in px[slab & touching]}
    assert all((x, y) in shared for (x, y) in px[slab & ~touching & at])
    assert red.sum() == len(shared)
    fig = example.figure()
    try:
        title = fig._suptitle.get_text()
        assert "frame 1" in title and f"{int(slab.sum())} of 800 particles in the slab" in title, title
        assert f"{int((slab & touching).sum())} of them touching another" in title, title
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert len(labels) == 2 and "no other" in labels[0] and "touching another" in labels[1], labels
    finally:
        plt.close(fig)


@pytest.mark.parametrize("headless", [True, False])
def test_camera_orbit(device, headless, tmp_path):
    module = load_example("example_camera_orbit")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1500, methods=("hlbvh", "sweep_sah"), widths=(2, 4, 16), resolution=24,
                                 num_frames=36, headless=headless)
        for _ in range(3):
            example.step()
            example.render()
    assert example.frame == 3
    # Every tree at every width finds the reference's hits on every pixel (up to shared-edge ties).
    assert set(example.disagree) == {(m, k) for m in ("hlbvh", "sweep_sah") for k in (2, 4, 16)}
    assert all(v == 0 for v in example.disagree.values())
    assert all(len(v) == 3 for v in example.ms.values())
    lines = example.table().splitlines()
    assert len(lines) == 3 + len(example.trees)
    # The legend's "x binary" is the binary traversal's mean ms per frame (the first frame left
    # out) over the tree's.
    assert lines[-1].startswith("ms/frame: ")
    assert "x binary: the binary traversal's ms/frame over this tree's" in lines[-1]
    binary = np.mean(example.ms[("binary", "hlbvh")][1:])
    for (method, k), ms in example.ms.items():
        if method != "binary":
            row = next(line for line in lines if line.strip().startswith(f"{method} k={k} "))
            assert float(row.split()[3]) == pytest.approx(binary / np.mean(ms[1:]), abs=0.006), row
    # The orbit turns: the first and the last frame differ.
    assert not np.array_equal(example.camera(0).eye, example.camera(2).eye)
    if headless:
        assert example.save(tmp_path) == []
    else:
        paths = example.save(tmp_path)
        assert [p.name for p in paths] == ["camera_orbit.png", "camera_orbit.gif"]
        assert all(p.stat().st_size > 0 for p in paths)
        # Something was hit: the image is not all sky.
        assert (example.image[..., 0] != example.image[0, 0, 0]).any()


def test_mesh_contact(device, tmp_path):
    """Particles falling on the bending mesh stay out of it: after every frame each one lies at
    least (nearly) its radius from the surface, measured by a separate batched query on the
    frame's tree, and particles do land on it."""
    module = load_example("example_mesh_contact")
    import hlbvh_warp

    with wp.ScopedDevice(device):
        example = module.Example(num_tris=2000, num_particles=500, num_frames=12)
        for _ in range(6):
            example.step()
            _, distance, prim = hlbvh_warp.closest_point(example.builder.bvh, example.positions.numpy())
            # Two projections per substep settle all but particles wedged in a crease, which end
            # within a fraction of a percent of their radius (0.997 at worst in this scene).
            assert (prim >= 0).all() and distance.min() >= 0.99 * example.radius, distance.min() / example.radius
        path = example.render(tmp_path / "contact.png")
    assert sum(r["touching"] for r in example.rows) > 0
    assert {r["decision"] for r in example.rows} <= {"refit", "rebuild", "none"}
    assert len(example.table().splitlines()) == 7
    assert path.stat().st_size > 0


def test_mesh_contact_picture_says_what_it_shows():
    """The last frame's picture: its title names the frame and the particles touching, its
    legend the three colours, and every red pixel (read back from the PNG) lies on a particle
    that sits at its radius from the mesh (or within, in a crease) by a separate closest-point
    query: red marks contact, not a particle in flight."""
    import matplotlib.pyplot as plt

    import hlbvh_warp

    module = load_example("example_mesh_contact")
    example = module.Example(num_tris=2000, num_particles=500, num_frames=6)
    for _ in range(6):
        example.step()
    positions = example.positions.numpy()
    _, distance, _ = hlbvh_warp.closest_point(example.builder.bvh, positions)
    at_contact = distance <= 1.001 * example.radius
    touching = int(example.touching.numpy().sum())
    assert 0 < touching < len(positions) and at_contact.sum() >= touching
    fig = example.figure()
    try:
        title = fig._suptitle.get_text()
        assert "frame 6 of 6" in title and f"{touching} of 500 particles touching" in title, title
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert len(labels) == 3 and "mesh" in labels[0] and "clear" in labels[1] and "touching" in labels[2]
        across, up = example.mesh.length_axis, example.mesh.bend_axis
        contact = positions[at_contact]
        assert_red_on(fig, fig.axes[0], np.stack([contact @ across, contact @ up], axis=1), both_ways=False)
    finally:
        plt.close(fig)


def test_mesh_collision(device, tmp_path):
    """The copy passing through the mesh: every frame's intersecting pairs equal those of a fresh
    `sweep_sah` tree over the copy's vertices of that frame (so the Builder's per-frame tree is
    right), contact starts and ends clear of the mesh, and each pair's triangles do intersect by
    `triangles_intersect`."""
    module = load_example("example_mesh_collision")
    import hlbvh_warp

    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1500, num_frames=10)
        for _ in range(10):
            example.step()
            moving = example.position(example.frame).astype(np.float32)
            fresh = hlbvh_warp.build(moving, example.faces, method="sweep_sah")
            assert np.array_equal(example.pairs, hlbvh_warp.intersecting_pairs(example.resting, fresh))
            if len(example.pairs):
                tri_a = example.vertices.astype(np.float32)[example.faces[example.pairs[:, 0]]]
                tri_b = moving[example.faces[example.pairs[:, 1]]]
                assert hlbvh_warp.triangles_intersect(tri_a, tri_b).all()
        path = example.render(tmp_path / "collision.png")
    counts = [r["intersecting"] for r in example.rows]
    assert counts[0] == 0 and counts[-1] == 0 and max(counts) > 0, counts
    assert all(r["candidates"] >= r["intersecting"] for r in example.rows)
    assert len(example.table().splitlines()) == 11
    assert path.stat().st_size > 0


def test_mesh_collision_picture_says_what_it_shows(tmp_path):
    """The picture of the frame with the most contact: its title names that frame and its pair
    count, its legend the three colours, and its red pixels (read back from the PNG) fall on the
    centroids of the triangles of a fresh `sweep_sah` tree's intersecting pairs of that frame, and
    on nothing else. It had no title or legend: grey, blue and red were the reader's guess."""
    import matplotlib.pyplot as plt

    import hlbvh_warp

    module = load_example("example_mesh_collision")
    example = module.Example(num_tris=1500, num_frames=10)
    for _ in range(10):
        example.step()
    frame = 1 + int(np.argmax([r["intersecting"] for r in example.rows]))
    moving = example.position(frame)
    fresh = hlbvh_warp.build(moving.astype(np.float32), example.faces, method="sweep_sah")
    pairs = hlbvh_warp.intersecting_pairs(example.resting, fresh)
    centroids = np.concatenate([example.vertices[example.faces[np.unique(pairs[:, 0])]].mean(axis=1),
                                moving[example.faces[np.unique(pairs[:, 1])]].mean(axis=1)])
    fig = example.figure()
    try:
        title = fig._suptitle.get_text()
        assert f"frame {frame} of 10" in title and f"{len(pairs)} intersecting triangle pairs" in title, title
        labels = [t.get_text() for t in fig.legends[0].get_texts()]
        assert len(labels) == 3 and "resting" in labels[0] and "moving" in labels[1] and "intersect" in labels[2]
        ax = fig.axes[0]
        assert_red_on(fig, ax, centroids[:, [0, 2]])
    finally:
        plt.close(fig)


# Small runs of each script, so that one which ignores a bad option still ends quickly.
TINY_ARGS = {
    "example_exploding_mesh": ["--headless", "--num-frames", "1", "--num-tris", "500"],
    "example_bending_mesh": ["--headless", "--num-frames", "1", "--num-tris", "500"],
    "example_frame_timing": ["--headless", "--num-frames", "1", "--num-tris", "500", "--modes", "hlbvh scratch",
                             "--sequences", "explode"],
    "example_scene_builds": ["--headless", "--num-frames", "1"],
    "example_user_kernel": ["--headless", "--num-frames", "1", "--resolution", "8"],
    "example_particle_collisions": ["--headless", "--num-frames", "1", "--num-particles", "100"],
    "example_mesh_contact": ["--headless", "--num-frames", "1", "--num-particles", "100", "--num-tris", "500"],
    "example_mesh_collision": ["--headless", "--num-frames", "1", "--num-tris", "500"],
    "example_camera_orbit": ["--headless", "--num-frames", "1", "--num-tris", "300", "--resolution", "8",
                             "--methods", "hlbvh", "--widths", "2"],
}


#: The examples that read a --mesh, and those that write to --out (the folder's, or the picture's path).
MESH_EXAMPLES = ["example_exploding_mesh", "example_bending_mesh", "example_frame_timing", "example_scene_builds",
                 "example_mesh_contact", "example_mesh_collision", "example_camera_orbit"]
OUT_FOLDER_EXAMPLES = ["example_exploding_mesh", "example_bending_mesh", "example_frame_timing",
                       "example_particle_collisions", "example_camera_orbit", "example_mesh_contact",
                       "example_mesh_collision", "example_user_kernel"]


def without_headless(args):
    # Headless runs write nothing, so --out is checked only where it will be written.
    return [a for a in args if a != "--headless"]


def argument_error(name, argv, capsys, monkeypatch=None) -> str:
    """The one-line error of ``examples/<name>.py argv`` (run in-process through its ``main``),
    which must exit with status 2 before an `Example` is made."""
    module = load_example(name)
    if monkeypatch is not None:
        def no_work(*args, **kwargs):
            raise AssertionError("the example started its work before the arguments were checked")

        monkeypatch.setattr(module, "Example", no_work)
    with pytest.raises(SystemExit) as exit_:
        module.main(argv)
    err = capsys.readouterr().err
    assert exit_.value.code == 2, (name, argv, exit_.value.code, err)
    last = err.strip().splitlines()[-1]
    assert "Traceback" not in err and ": error: " in last, err
    return last


@pytest.mark.parametrize("name,extra,message", [
    *[(name, ["--num-frame-count", "2"], "unrecognized arguments: --num-frame-count") for name in TINY_ARGS],
    ("example_scene_builds", ["--scratch-sets", "-1"], "--scratch-sets: must be at least 0"),
    ("example_bending_mesh", ["--sah-growth-limit", "-1"], "--sah-growth-limit: must be a number >= 0"),
])
def test_example_scripts_reject_bad_options_in_one_line(name, extra, message, capsys, monkeypatch):
    # A misspelt option used to be ignored (the run went on with the default) and a negative
    # count or limit ended in a library traceback.
    assert message in argument_error(name, [*TINY_ARGS[name], *extra], capsys, monkeypatch)


@pytest.mark.parametrize("name", list(TINY_ARGS))
@pytest.mark.parametrize("device_arg", ["foo", "cuda:99"] + ([] if wp.is_cuda_available() else ["cuda"]))
def test_example_scripts_reject_a_device_this_machine_lacks(name, device_arg, capsys, monkeypatch):
    # --device was a plain string handed to wp.ScopedDevice: a traceback from Warp.
    err = argument_error(name, [*TINY_ARGS[name], "--device", device_arg], capsys, monkeypatch)
    assert "argument --device:" in err and ("Invalid device identifier" in err or "CUDA" in err), err


def not_meshes(folder: pathlib.Path) -> list:
    """(file, what its error must say): files that pass `cli.mesh_file` (they exist) but are no mesh."""
    text = folder / "notes.txt"
    text.write_text("not a mesh\n")
    cut_short = folder / "cut_short.ply"
    cut_short.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n")
    garbage = folder / "garbage.ply"
    garbage.write_text("garbage\n")
    points = folder / "points.ply"
    points.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                      "property float z\nend_header\n0 0 0\n1 0 0\n0 1 0\n")
    bad_face = folder / "bad_face.ply"
    bad_face.write_text("ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
                        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
                        "0 0 0\n1 0 0\n0 1 0\n3 0 1 9\n")
    return [(text, "file_type 'txt' not supported"), (cut_short, "trimesh could not read the mesh"),
            (garbage, "Not a ply file"), (points, "the mesh has no triangles"),
            (bad_face, "face index 9 out of range")]


@pytest.mark.parametrize("name", MESH_EXAMPLES)
def test_example_scripts_name_a_mesh_file_they_cannot_read(name, tmp_path, capsys, monkeypatch):
    # A file that exists but is no mesh passed the --mesh check and failed as a traceback when
    # the first Example loaded it (trimesh's NotImplementedError or ValueError).
    for path, problem in not_meshes(tmp_path):
        err = argument_error(name, [*TINY_ARGS[name], "--mesh", str(path)], capsys, monkeypatch)
        assert f"error: {path}: " in err and problem in err, (name, path, err)


@pytest.mark.parametrize("name", OUT_FOLDER_EXAMPLES)
def test_example_scripts_check_out_before_the_first_frame(name, tmp_path, capsys, monkeypatch):
    # --out /dev/null/x (or a file where a folder goes) ended in NotADirectoryError after every frame.
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    args = without_headless(TINY_ARGS[name])
    cases = [(a_file / "x", f"--out {a_file / 'x'}: cannot make the folder, {a_file} is a file"),
             (a_file, f"--out {a_file} is a file, not a folder")]
    for out, message in cases:
        assert message in argument_error(name, [*args, "--out", str(out)], capsys, monkeypatch)
    assert a_file.read_text() == "" and sorted(p.name for p in tmp_path.iterdir()) == ["a_file"]


def test_every_picture_writing_example_writes_into_one_default_folder(capsys, monkeypatch):
    # Each example's --out is a folder, hlbvh_example_out unless given: the collision and contact
    # pictures went to bare .png files in the current folder, the orbit to camera_orbit_out, and
    # the user kernel's frames to the current folder with no option at all.
    monkeypatch.setattr(sys, "argv", ["example"])
    for name in OUT_FOLDER_EXAMPLES:
        with pytest.raises(SystemExit):
            load_example(name).main(["--help"])
        words = " ".join(capsys.readouterr().out.split())
        options = words[words.index("options:"):]
        out = options[options.index("--out OUT"):].split(" --")[0]
        assert out.startswith("--out OUT Folder") and out.endswith("(default: hlbvh_example_out)"), (name, out)


def test_mesh_pictures_go_into_their_out_folder(tmp_path):
    # The collision and contact examples end as the others do: their picture in --out.
    for name, picture in (("example_mesh_collision", "mesh_collision.png"),
                          ("example_mesh_contact", "mesh_contact.png")):
        args = [*without_headless(TINY_ARGS[name]), "--out", str(tmp_path / "pictures")]
        run = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), *args],
                             capture_output=True, text=True, cwd=tmp_path, timeout=600)
        assert run.returncode == 0, run.stderr
        assert (tmp_path / "pictures" / picture).stat().st_size > 0
        assert f"wrote {tmp_path / 'pictures' / picture}" in run.stdout
        # Each table is followed by the line that says what its columns mean.
        assert "tree: what the" in run.stdout and "ms: " in run.stdout


@pytest.mark.parametrize("methods,message", [
    ("foo", "unknown builder(s) ['foo'] in --methods"),
    ("hlbvh,foo", "unknown builder(s) ['foo'] in --methods"),
    ("", "--methods '' names no builder"),
    (" , ", "--methods ' , ' names no builder"),
])
def test_camera_orbit_checks_its_builders_first(methods, message, capsys, monkeypatch):
    # Both used to end in a traceback: build()'s ValueError, or indexing an empty method list.
    args = list(TINY_ARGS["example_camera_orbit"])
    args[args.index("--methods") + 1] = methods
    assert message in argument_error("example_camera_orbit", args, capsys, monkeypatch)


def test_example_scripts_run_main_as_scripts(tmp_path):
    # The in-process tests call main(); each script must also call it, and end a bad argument
    # without a traceback when run as a program (one subprocess: each costs Warp's start-up).
    for name in TINY_ARGS:
        assert (EXAMPLES / f"{name}.py").read_text().rstrip().endswith('if __name__ == "__main__":\n    main()'), name
    name = "example_exploding_mesh"
    run = subprocess.run([sys.executable, str(EXAMPLES / f"{name}.py"), *TINY_ARGS[name], "--device", "foo"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 2 and "argument --device: Invalid device identifier: foo" in run.stderr, run.stderr
    assert "Traceback" not in run.stderr


def test_example_scripts_hand_the_mesh_they_checked_to_the_example(tmp_path, capsys, monkeypatch):
    # main() reads --mesh once, before any work, and the Example takes the arrays it read.
    import trimesh

    path = tmp_path / "ball.obj"
    trimesh.creation.icosphere(subdivisions=2).export(path)
    module = load_example("example_exploding_mesh")
    made = []

    class Recorded(module.Example):
        def __init__(self, *args, **kwargs):
            super().__init__(*args, **kwargs)
            made.append(self)

    monkeypatch.setattr(module, "Example", Recorded)
    module.main(["--headless", "--num-frames", "1", "--mesh", str(path)])
    assert len(made) == 1 and len(made[0].mesh.faces) == 320
    load_example("example_scene_builds").main(["--headless", "--num-frames", "1", "--mesh", str(path),
                                               "--mesh", str(path)])
    assert "2 meshes (320, 320 triangles)" in capsys.readouterr().out


# ----------------------------------------------------------------- pinned by the third mutation audit
COUNT_OPTIONS = [
    *[(name, "--num-frames") for name in TINY_ARGS],
    ("example_exploding_mesh", "--image-size"), ("example_bending_mesh", "--image-size"),
    ("example_mesh_contact", "--num-particles"), ("example_particle_collisions", "--num-particles"),
    ("example_user_kernel", "--resolution"), ("example_camera_orbit", "--resolution"),
]
NON_NEGATIVE_OPTIONS = [("example_frame_timing", "--cpu-threads"), ("example_frame_timing", "--subdivide"),
                        ("example_scene_builds", "--scratch-sets")]


@pytest.mark.parametrize("name,option,value,message", [
    *[(name, option, "0", f"argument {option}: must be at least 1, got 0") for name, option in COUNT_OPTIONS],
    *[(name, option, "-1", f"argument {option}: must be at least 0, got -1") for name, option in NON_NEGATIVE_OPTIONS],
    # The generated scene's least (`scenes.MIN_SCENE_TRIS`), not 1.
    *[(name, "--num-tris", "0", "argument --num-tris: must be at least 18, got 0")
      for name in ("example_exploding_mesh", "example_bending_mesh", "example_frame_timing", "example_mesh_contact",
                   "example_mesh_collision", "example_camera_orbit")],
])
def test_example_scripts_refuse_counts_below_their_least(name, option, value, message, capsys, monkeypatch):
    # A count of 0 (or -1 where 0 is allowed) ran no frame, or failed in the library as a traceback.
    assert message in argument_error(name, [*TINY_ARGS[name], f"{option}={value}"], capsys, monkeypatch)


@pytest.mark.parametrize("value", ["-1", "nan", "-inf", "x"])
def test_frame_timing_refuses_a_global_sort_threshold_below_zero(value, capsys, monkeypatch):
    # The BuildConfig refused it only after the arguments were accepted, as a traceback.
    err = argument_error("example_frame_timing", [*TINY_ARGS["example_frame_timing"], f"--global-sort-runs={value}"],
                         capsys, monkeypatch)
    assert "argument --global-sort-runs: must be a number" in err, err


def test_frame_timing_gives_its_builders_the_global_sort_threshold(device):
    """``--global-sort-runs 1``: every build takes the paper's compress-sort-decompress, the
    setting the paper compares resorting in (the stages say which sort ran)."""
    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1000, num_frames=1, sequences=("bend",),
                                 modes=["hlbvh scratch", "hlbvh resorted"], headless=True, stages=True,
                                 global_sort_runs=1.0)
        example.step()
    for label, runner in example.sequences["bend"]["runners"].items():
        assert runner.config.global_sort_runs == 1.0
        stages = example.sequences["bend"]["stages"][label][0]
        assert "global_sort" not in stages and "run_length_decode" in stages, (label, stages)


@pytest.mark.parametrize("widths", ["1", "2,32", "2,x", "", "2,,4", "4,-8"])
def test_camera_orbit_checks_its_widths_first(widths, capsys, monkeypatch):
    # Only branching factors the wide trees have (2 to 16), every word of the list one of them
    # (a word dropped silently ran fewer widths; a factor of 1 or 32 failed in the first collapse).
    args = list(TINY_ARGS["example_camera_orbit"])
    args[args.index("--widths") + 1] = widths
    err = argument_error("example_camera_orbit", args, capsys, monkeypatch)
    assert f"--widths takes branching factors from 2 to 16, got {widths}".strip() in err, err


@pytest.mark.parametrize("option,value,message", [
    ("--modes", "hlbvh scratch,hlbvh nothing", "unknown mode(s) ['hlbvh nothing']"),
    ("--sequences", "explode,wobble", "unknown sequence(s) ['wobble']"),
])
def test_frame_timing_checks_its_modes_and_sequences_first(option, value, message, capsys, monkeypatch):
    args = list(TINY_ARGS["example_frame_timing"])
    args[args.index(option) + 1] = value
    assert message in argument_error("example_frame_timing", args, capsys, monkeypatch)


@pytest.mark.parametrize("value", ["nan", "-0.5", "-inf"])
def test_bending_refuses_a_growth_limit_that_is_no_limit(value, capsys, monkeypatch):
    err = argument_error("example_bending_mesh", [*TINY_ARGS["example_bending_mesh"], f"--sah-growth-limit={value}"],
                         capsys, monkeypatch)
    assert f"--sah-growth-limit: must be a number >= 0, got {value}" in err, err


def test_frame_timing_checks_its_plot_folder_even_headless(tmp_path, capsys, monkeypatch):
    # The plot is written headless too, so --out is checked before the first frame either way.
    a_file = tmp_path / "a_file"
    a_file.write_text("")
    args = [*TINY_ARGS["example_frame_timing"], "--out", str(a_file)]
    assert "--headless" in args
    assert f"--out {a_file} is a file, not a folder" in argument_error("example_frame_timing", args, capsys,
                                                                        monkeypatch)


@pytest.mark.parametrize("name", [name for name, args in TINY_ARGS.items() if "--num-tris" in args])
def test_example_scripts_refuse_a_scene_too_small_to_generate(name, capsys, monkeypatch):
    """`--num-tris 5` (a tiny mesh to try the per-frame loop on) ended in a ValueError traceback
    from `default_scene` after the arguments were accepted; the generated scene needs 18."""
    args = TINY_ARGS[name]
    at = args.index("--num-tris")
    last = argument_error(name, args[:at] + ["--num-tris", "5"] + args[at + 2:], capsys, monkeypatch)
    assert "--num-tris: must be at least 18" in last, last


def test_order_disorder_against_a_plain_count():
    """`--order-stats`' measure against a count in plain Python: the codes of this frame fed in
    the stable order of the last frame's, their descending adjacent pairs, and each primitive's
    distance from its place among them sorted (stably, ties kept in fed order)."""
    module = load_example("example_frame_timing")
    rng = np.random.default_rng(5)
    last = rng.integers(0, 40, 300)
    codes = last + rng.integers(-6, 7, 300)
    fed = [int(codes[i]) for i in sorted(range(300), key=lambda i: (last[i], i))]
    descending = sum(b < a for a, b in zip(fed, fed[1:])) / 299
    ranked = sorted(range(300), key=lambda i: (fed[i], i))
    distance = [abs(ranked.index(i) - i) for i in range(300)]
    got = module.order_disorder(codes, last)
    assert got[0] == pytest.approx(descending) and got[1] == pytest.approx(np.median(distance))
    assert got[2] == pytest.approx(np.mean(distance)) and got[3] == pytest.approx(np.percentile(distance, 99))
    assert module.order_disorder(codes, codes) == (0.0, 0.0, 0.0, 0.0)


def test_frame_timing_order_stats(device):
    """At rest the last frame's order is this frame's sorted order; an explosion scrambles it."""
    module = load_example("example_frame_timing")
    with wp.ScopedDevice(device):
        example = module.Example(num_tris=1000, num_frames=2, sequences=("static", "explode"),
                                 modes=["hlbvh scratch"], headless=True, order_stats=True)
        for _ in range(2):
            example.step()
    assert example.sequences["static"]["order"] == [(0.0, 0.0, 0.0, 0.0)] * 2
    assert all(row[0] > 0.0 and row[2] > 0.0 for row in example.sequences["explode"]["order"])
    lines = example.order_table().splitlines()
    assert lines[1].split()[0] == "static" and float(lines[1].split()[1]) == 0.0


@pytest.mark.parametrize("name,option,limit", [
    ("example_exploding_mesh", "--image-size", "4096"), ("example_bending_mesh", "--image-size", "4096"),
    ("example_camera_orbit", "--resolution", "4096"), ("example_user_kernel", "--resolution", "4096"),
    ("example_particle_collisions", "--num-particles", "16777216"),
    ("example_mesh_contact", "--num-particles", "16777216"),
    ("example_frame_timing", "--subdivide", "14"),
])
def test_example_scripts_refuse_sizes_past_their_bound(name, option, limit, capsys, monkeypatch):
    """`--image-size 100000` (and `--resolution`, `--num-particles 1e11`, `--subdivide 40`) ended in
    a MemoryError or Warp's allocation traceback, naming no option: the examples take the bounds
    of the command line (`cli.MAX_IMAGE_SIDE`, `cli.MAX_QUERIES`, a tree's 2^30 triangles)."""
    last = argument_error(name, [*TINY_ARGS[name], option, str(int(limit) + 1)], capsys, monkeypatch)
    assert f"argument {option}: must be at most {limit}" in last, last


@pytest.mark.parametrize("name,option", [("example_exploding_mesh", "--image-size"),
                                         ("example_bending_mesh", "--image-size"),
                                         ("example_camera_orbit", "--resolution")])
def test_animated_examples_bound_the_frames_they_keep_for_the_gif(name, option, capsys, monkeypatch):
    # Every rendered frame is kept for the GIF: 1000 frames of 4096^2 pixels are 50 GB.
    args = [*without_headless(TINY_ARGS[name]), "--num-frames", "1000", option, "4096"]
    last = argument_error(name, args, capsys, monkeypatch)
    assert "pixels of frames for the GIF" in last and "--num-frames 1000" in last, last
    # Headless runs keep no frame: the same sizes reach the Example (replaced here by one that fails).
    module = load_example(name)
    monkeypatch.setattr(module, "Example", lambda *a, **k: pytest.fail("started", pytrace=False))
    with pytest.raises(pytest.fail.Exception, match="started"):
        module.main([*args, "--headless"])


def test_frame_timing_bounds_subdivide_by_the_meshs_size(capsys, monkeypatch):
    # 60000 triangles split 7 times are 983M (under 2^30), 8 times 3.9G: more than a tree holds.
    args = [*TINY_ARGS["example_frame_timing"], "--num-tris", "60000", "--subdivide", "8"]
    last = argument_error("example_frame_timing", args, capsys, monkeypatch)
    assert "--subdivide 8:" in last and "a tree holds fewer than 2^30 triangles" in last, last


def test_mesh_collision_at_any_scale(tmp_path, capsys, monkeypatch):
    """The same mesh scaled by 2^70 (coordinates near 1e21, well inside float32) collides as the
    mesh itself, frame by frame: a power of two scales every coordinate exactly. The diagonal was
    taken in float32, whose squares overflow past 1.8e19: it came out inf, the copy's first
    position -inf, and the run ended in the Builder's "vertices has a NaN or Inf coordinate"
    traceback. A mesh whose moving copy does leave float32's range (coordinates of 3e38) is an
    argument error naming the file."""
    import trimesh

    module = load_example("example_mesh_collision")
    ball = trimesh.creation.icosphere(subdivisions=2)
    vertices, faces = np.asarray(ball.vertices, np.float32), np.asarray(ball.faces, np.int32)
    rows = []
    for scale in (1.0, 2.0 ** 70):
        example = module.Example((vertices * np.float32(scale), faces), num_frames=8, headless=True)
        for _ in range(8):
            example.step()
        rows.append([(r["candidates"], r["intersecting"]) for r in example.rows])
    assert rows[0] == rows[1] and max(i for _, i in rows[0]) > 0, rows
    huge = tmp_path / "huge.ply"
    trimesh.Trimesh(vertices * 3e38, faces, process=False).export(huge)
    last = argument_error("example_mesh_collision", [*TINY_ARGS["example_mesh_collision"], "--mesh", str(huge)],
                          capsys, monkeypatch)
    assert f"{huge}: " in last and "float32" in last, last


def test_mesh_contact_at_a_large_scale(tmp_path, capsys, monkeypatch):
    """The generated scene scaled by 2^70 (coordinates near 1e21, well inside float32): the
    particles land on it and stay out of it, as at scale 1. The diagonal was taken in float32,
    whose squares overflow past 1.8e19: gravity came out NaN, every particle NaN, and no particle
    ever touched the mesh, silently. A mesh whose particles would leave float32's range
    (coordinates of 3e38) is an argument error naming the file."""
    import trimesh

    import hlbvh_warp
    from hlbvh_warp.scenes import default_scene

    module = load_example("example_mesh_contact")
    vertices, faces = default_scene(num_tris=2000)
    example = module.Example((vertices * np.float32(2.0 ** 70), faces), num_particles=500, num_frames=12,
                             headless=True)
    for _ in range(4):
        example.step()
        positions = example.positions.numpy()
        assert np.isfinite(positions).all()
        _, distance, prim = hlbvh_warp.closest_point(example.builder.bvh, positions)
        assert (prim >= 0).all() and distance.min() >= 0.99 * example.radius, distance.min() / example.radius
    assert sum(r["touching"] for r in example.rows) > 0, example.rows
    huge = tmp_path / "huge.ply"
    trimesh.Trimesh(vertices * np.float32(1e38), faces, process=False).export(huge)
    last = argument_error("example_mesh_contact", [*TINY_ARGS["example_mesh_contact"], "--mesh", str(huge)],
                          capsys, monkeypatch)
    assert f"{huge}: " in last and "float32" in last, last


@pytest.mark.parametrize("name", sorted(p.stem for p in EXAMPLES.glob("example_*.py")) + ["demo"])
def test_every_option_has_help_with_one_default(name, capsys, monkeypatch):
    # `--help` as a user reads it: an option with no help text showed no default either
    # (--method, --policy, --image-size, --num-particles), and one whose text named its default
    # got argparse's "(default: None)" after it ("A mesh file (default: the generated scene).
    # (default: None)").
    import re

    monkeypatch.setattr(sys, "argv", [name])
    if name == "demo":
        from hlbvh_warp import cli

        run = lambda: cli.main(["demo", "--help"])  # noqa: E731
    else:
        module = load_example(name)
        run = lambda: module.main(["--help"])  # noqa: E731
    with pytest.raises(SystemExit):
        run()
    text = capsys.readouterr().out
    options = text[text.index("options:"):]
    # One entry per option: its flag line and the indented lines of its text, joined.
    entries = re.split(r"\n  (?=-)", options)[1:]
    assert entries, text
    for entry in entries:
        flag, _, help_text = entry.partition("  ")
        words = " ".join(entry.split())
        assert help_text.strip() or "\n" in entry, f"{flag.strip()}: no help text"
        # A default of None is the text's to describe ("Warp's default", "the generated scene").
        assert "(default: None)" not in words, words
        assert words.count("(default:") <= 1, words
