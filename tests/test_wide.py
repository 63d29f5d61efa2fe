"""Wide BVHs: the collapse against a NumPy collapse of the same binary tree, node boxes against
the triangles, the SAH against a float64 recursion, rays against the float64 brute force."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

import hlbvh_warp as hw
from hlbvh_warp import metrics, wide
from handmade_trees import caterpillar
from oracles import brute_force_closest_hit, random_rays, random_soup

WIDTHS = [2, 3, 4, 8, 16]


def numpy_collapse(tree: dict, width: int):
    """Greedy collapse in plain Python: {wide node's binary id: sorted child (begin, end) ranges}."""
    left, right = tree["node_left"], tree["node_right"]
    lo, hi = tree["node_lowers"].astype(np.float64), tree["node_uppers"].astype(np.float64)
    begin, end = tree["node_begin"], tree["node_end"]

    def area(n):
        d = hi[n] - lo[n]
        return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])

    out, todo = {}, [0]
    while todo:
        b = todo.pop()
        children = [left[b], right[b]] if left[b] >= 0 else [b]
        while len(children) < width:
            interior = [c for c in children if left[c] >= 0]
            if not interior:
                break
            # Largest area first (float64, as the kernel compares them), ties to the earlier slot.
            areas = [area(c) for c in interior]
            pick = interior[int(np.argmax(areas))]
            children[children.index(pick)] = left[pick]
            children.append(right[pick])
        out[b] = sorted((begin[c], end[c]) for c in children)
        todo += [c for c in children if left[c] >= 0]
    return out


def wide_nodes(w: dict, width: int):
    """The wide tree as {node: [(child kind, begin, end, lower, upper), ...]}."""
    num = len(w["wide_begin"])
    nodes = {}
    for n in range(num):
        slots = []
        for j in range(width):
            s = n * width + j
            if w["slot_child"][s] != -2:
                slots.append((int(w["slot_child"][s]), int(w["slot_begin"][s]), int(w["slot_end"][s]),
                              w["slot_lowers"][s], w["slot_uppers"][s]))
        nodes[n] = slots
    return nodes


@pytest.mark.parametrize("width", WIDTHS)
@pytest.mark.parametrize("method, leaf", [("hlbvh", 1), ("sweep_sah", 1), ("median", 3)])
def test_collapse_structure_and_boxes(device, rng, width, method, leaf):
    v, f = random_soup(rng, 150, scale=0.2)
    bvh = hw.build(v, f, method=method, device=device, config=hw.BuildConfig(max_leaf_size=leaf))
    w = wide.collapse(bvh, width).to_numpy()
    nodes = wide_nodes(w, width)
    tri = v[f].astype(np.float64)
    order = w["prim_order"]
    leaves = []
    for n, slots in nodes.items():
        assert 2 <= len(slots) <= width
        # A node's range is its children's ranges laid end to end.
        ranges = sorted((b, e) for _, b, e, _, _ in slots)
        assert ranges[0][0] == w["wide_begin"][n] and ranges[-1][1] == w["wide_end"][n]
        assert all(a[1] == b[0] for a, b in zip(ranges, ranges[1:]))
        for kind, b, e, lo, hi in slots:
            # Each slot's box is the exact box of its triangles.
            ids = order[b:e]
            np.testing.assert_array_equal(lo, tri[ids].min(axis=(0, 1)).astype(np.float32))
            np.testing.assert_array_equal(hi, tri[ids].max(axis=(0, 1)).astype(np.float32))
            if kind >= 0:
                assert (w["wide_begin"][kind], w["wide_end"][kind]) == (b, e)
            else:
                assert kind == -1 and 1 <= e - b <= leaf
                leaves.append((b, e))
    # The leaves cover every position once.
    covered = np.zeros(len(f), int)
    for b, e in leaves:
        covered[b:e] += 1
    assert (covered == 1).all()
    # Every wide node's children are the ones the greedy rule picks from the binary tree.
    expected = numpy_collapse(bvh.to_numpy(), width)
    got = {n: sorted((b, e) for _, b, e, _, _ in slots) for n, slots in nodes.items()}
    assert sorted(got.values()) == sorted(expected.values())


def numpy_wide_sah(w: dict, width: int, t1=1.0, t2=1.0):
    nodes = wide_nodes(w, width)

    def area(lo, hi):
        d = np.asarray(hi, np.float64) - np.asarray(lo, np.float64)
        return 2.0 * (d[0] * d[1] + d[1] * d[2] + d[2] * d[0])

    def cost(n, node_area):
        total = t1 * len(nodes[n])
        for kind, b, e, lo, hi in nodes[n]:
            child = cost(kind, area(lo, hi)) if kind >= 0 else t2 * (e - b)
            total += child * area(lo, hi) / node_area
        return total

    slots = nodes[0]
    root_lo = np.min([s[3] for s in slots], axis=0)
    root_hi = np.max([s[4] for s in slots], axis=0)
    return cost(0, area(root_lo, root_hi))


@pytest.mark.parametrize("width", WIDTHS)
def test_wide_sah_against_a_recursion(device, rng, width):
    v, f = random_soup(rng, 120, scale=0.3)
    bvh = hw.build(v, f, method="hlbvh_sah", device=device)
    w = wide.collapse(bvh, width)
    assert wide.sah_cost(w, 1.2, 1.0) == pytest.approx(numpy_wide_sah(w.to_numpy(), width, 1.2, 1.0), rel=1e-9)
    if width == 2:
        # The binary tree itself in the wide layout.
        assert w.num_nodes == len(f) - 1
        assert wide.sah_cost(w) == pytest.approx(metrics.sah_cost(bvh), rel=1e-9)


@pytest.mark.parametrize("width", [2, 4, 8, 16])
def test_wide_rays_match_the_brute_force(device, rng, width):
    v, f = random_soup(rng, 400, scale=0.15)
    bvh = hw.build(v, f, method="hlbvh", device=device)
    w = wide.collapse(bvh, width)
    o, d = random_rays(rng, v, 600)
    t, prim, stats = wide.intersect(w, o, d, stats=True)
    t_ref, prim_ref = brute_force_closest_hit(v, f, o, d)
    assert (prim_ref >= 0).sum() > 100
    from hlbvh_warp.reference import count_mismatches

    assert count_mismatches(t, prim, t_ref, prim_ref) == 0
    hits = prim >= 0
    assert (stats.prims_tested[hits] >= 1).all()
    assert (stats.boxes_tested <= stats.nodes_visited * width).all()
    # Bounded t: only hits before t_max count.
    cut = float(np.median(t_ref[prim_ref >= 0]))
    t2, prim2 = wide.intersect(w, o, d, t_max=cut)
    keep = (prim_ref >= 0) & (t_ref < cut * (1 - 1e-5))
    assert (prim2[keep] >= 0).all()
    assert (prim2[(prim_ref < 0) | (t_ref > cut * (1 + 1e-5))] < 0).all()



@wp.kernel
def _user_wide_rays(view: wide.WideView, origins: wp.array(dtype=wp.vec3), directions: wp.array(dtype=wp.vec3),
                    t_max: wp.array(dtype=float), hit_t: wp.array(dtype=float), hit_prim: wp.array(dtype=wp.int32)):
    i = wp.tid()
    h = wide.bvh_wide_closest_hit(view, origins[i], directions[i], t_max[i])
    hit_t[i] = h.t
    hit_prim[i] = h.prim


@pytest.mark.parametrize("width", [2, 4, 16])
def test_wide_rays_with_a_limit_per_ray_and_from_a_user_kernel(device, rng, width):
    """One t_max per ray (half of the hits cut off before the triangle, half after), through
    `wide.intersect` and through `bvh_wide_closest_hit` in a user kernel, against the brute force."""
    from hlbvh_warp.reference import count_mismatches

    v, f = random_soup(rng, 300, scale=0.15)
    bvh = hw.build(v, f, method="hlbvh", device=device)
    w = wide.collapse(bvh, width)
    o, d = random_rays(rng, v, 500)
    t_ref, prim_ref = brute_force_closest_hit(v, f, o, d)
    hits = prim_ref >= 0
    assert hits.sum() > 100
    # Far from every hit distance, so float32 rounding of a limit cannot decide.
    limits = np.where(np.arange(len(o)) % 2 == 0, 0.5, 1.5) * np.where(hits, t_ref, rng.uniform(0.1, 5.0, len(o)))
    t_cut, prim_cut = brute_force_closest_hit(v, f, o, d, t_max=limits)
    assert 0 < (prim_cut >= 0).sum() < hits.sum()
    t, prim = wide.intersect(w, o, d, t_max=limits)
    assert count_mismatches(t, prim, t_cut, prim_cut) == 0
    view = wide.view(w)
    assert wide.view(w) is view  # made once per wide tree
    n = len(o)
    out_t, out_prim = wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device)
    wp.launch(_user_wide_rays, dim=n, device=device,
              inputs=[view, wp.array(o, dtype=wp.vec3, device=device), wp.array(d, dtype=wp.vec3, device=device),
                      wp.array(limits, dtype=float, device=device), out_t, out_prim])
    assert np.array_equal(out_prim.numpy(), prim) and np.array_equal(out_t.numpy(), t)
    # A wrong number of limits names the shape, not the values.
    with pytest.raises(ValueError, match=r"shape \(500,\), got \(3,\)"):
        wide.intersect(w, o, d, t_max=np.ones(3))


def test_launch_args_check_their_limits(device):
    """`launch_args` (what the bench and the camera example launch with) takes a limit as
    `intersect` does, and a Warp array of limits only when the kernel can read it whole: a wrong
    length would read past its end, another dtype would fail inside Warp."""
    from hlbvh_warp.kernels import wide as wide_kernels

    sphere = hw.build(trimesh_icosphere(), device=device)
    w = wide.collapse(sphere, 4)
    n = 10
    o = wp.zeros(n, dtype=wp.vec3, device=device)
    d = wp.array(np.tile([0.0, 0.0, 1.0], (n, 1)), dtype=wp.vec3, device=device)
    out_t, out_prim = wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device)
    no_counts = wp.empty(0, dtype=wp.vec3i, device=device)
    for bad in (wp.zeros(0, dtype=float, device=device), wp.zeros(2, dtype=float, device=device),
                wp.zeros(n, dtype=wp.float64, device=device), wp.zeros((n, 1), dtype=float, device=device)):
        with pytest.raises(ValueError, match="t_max as a Warp array"):
            wide.launch_args(w, o, d, bad, out_t, out_prim, no_counts)
    # The sphere lies at t of about 1 (0.95-1) from its centre: limits of 0.5 miss, 2.0 hit.
    limits = np.where(np.arange(n) % 2 == 0, 0.5, 2.0)
    for given, kernel in ((limits, wide_kernels.wide_closest_hit_limits_kernel),
                          (wp.array(limits, dtype=float, device=device), wide_kernels.wide_closest_hit_limits_kernel),
                          (2.0, wide_kernels.wide_closest_hit_kernel),
                          (np.array([2.0]), wide_kernels.wide_closest_hit_kernel)):
        chosen, args = wide.launch_args(w, o, d, given, out_t, out_prim, no_counts)
        assert chosen is kernel  # one limit goes by value
        wp.launch(chosen, dim=n, device=device, inputs=args)
        expect = limits > 1.0 if kernel is wide_kernels.wide_closest_hit_limits_kernel else np.full(n, True)
        assert np.array_equal(out_prim.numpy() >= 0, expect)
        t, prim = wide.intersect(w, o.numpy(), d.numpy(), t_max=limits if np.size(given) == n else 2.0)
        assert np.array_equal(prim, out_prim.numpy()) and np.array_equal(t, out_t.numpy())
    # The one-limit kernel keeps its name and takes a limit as a float parameter takes one (the
    # inputs of the call before `launch_args` still serve it).
    args = wide.launch_inputs(w, o, d, 2.0, out_t, out_prim, no_counts)
    for limit, hits in ((2, True), (np.float32(0.5), False), (np.float64(2.0), True)):
        args[3] = limit
        wp.launch(wide_kernels.wide_closest_hit_kernel, dim=n, device=device, inputs=args)
        assert ((out_prim.numpy() >= 0) == hits).all(), limit
    with pytest.raises(ValueError, match="launch_args"):
        wide.launch_inputs(w, o, d, limits, out_t, out_prim, no_counts)


def test_launch_args_check_every_array_the_kernel_reads(device):
    """A user launches what `launch_args` returns over ``len(origins)`` threads: an array shorter
    than that was read or written past its end (outputs and counts crashed the process), so each
    is refused, as are arrays of another type or device and lists; the right arrays still hit."""
    sphere = hw.build(trimesh_icosphere(), device=device)
    w = wide.collapse(sphere, 4)
    n = 8
    o = wp.zeros(n, dtype=wp.vec3, device=device)
    d = wp.array(np.tile([0.0, 0.0, 1.0], (n, 1)), dtype=wp.vec3, device=device)
    good = {"origins": o, "directions": d, "hit_t": wp.empty(n, dtype=float, device=device),
            "hit_prim": wp.empty(n, dtype=wp.int32, device=device),
            "counts": wp.empty(n, dtype=wp.vec3i, device=device)}
    bad = {"directions": [wp.array(np.array([[0.0, 0.0, 1.0]]), dtype=wp.vec3, device=device),
                          wp.zeros(n, dtype=wp.vec3d, device=device)],
           "hit_t": [wp.empty(1, dtype=float, device=device), wp.empty(n, dtype=wp.float64, device=device)],
           "hit_prim": [wp.empty(n - 1, dtype=wp.int32, device=device), wp.empty(n + 1, dtype=wp.int32, device=device)],
           "counts": [wp.empty(1, dtype=wp.vec3i, device=device), wp.empty(n, dtype=wp.vec3f, device=device)],
           "origins": [o.numpy()]}
    if device != "cpu":
        bad["hit_t"].append(wp.empty(n, dtype=float, device="cpu"))
    for name, arrays in bad.items():
        for array in arrays:
            given = dict(good, **{name: array})
            with pytest.raises(ValueError, match=name):
                wide.launch_args(w, given["origins"], given["directions"], 2.0, given["hit_t"], given["hit_prim"],
                                 given["counts"])
    with pytest.raises(ValueError, match="WideBvh"):
        wide.launch_args(sphere, o, d, 2.0, good["hit_t"], good["hit_prim"], good["counts"])
    kernel, args = wide.launch_args(w, o, d, 2.0, good["hit_t"], good["hit_prim"], good["counts"])
    wp.launch(kernel, dim=n, device=device, inputs=args)
    t, prim = wide.intersect(w, o.numpy(), d.numpy(), 2.0)
    assert (prim >= 0).all() and np.array_equal(good["hit_prim"].numpy(), prim)
    assert np.array_equal(good["hit_t"].numpy(), t) and (good["counts"].numpy()[:, 2] > 0).all()


def trimesh_icosphere():
    import trimesh

    return trimesh.creation.icosphere(subdivisions=2)


def test_a_wide_tree_refuses_host_calls_once_its_binary_tree_changed(device):
    """The view is made with the collapse, its root box the one the slots were cut from. The wide
    tree reads the binary tree's primitive order and triangles, so after a refit or rebuild of that
    tree (a frame that answered 39% of rays like the current frame) every host call refuses it and
    says to collapse again; a frame in which nothing moved leaves it usable."""
    mesh = trimesh_icosphere()
    builder = hw.Builder(len(mesh.faces), device=device, policy="auto")
    builder.build(mesh.vertices, mesh.faces)
    w = wide.collapse(builder.bvh, 4)
    made = w._view
    root_slots_upper = w.slot_uppers.numpy()[:4][w.slot_child.numpy()[:4] != kernels_empty()].max(axis=0)
    assert np.array_equal(np.array(made.root_upper), root_slots_upper)
    o, d = np.float32([[0.11, 0.13, -5.0]]), np.float32([[0.0, 0.0, 1.0]])  # off every edge
    builder.update(np.asarray(mesh.vertices))  # nothing moved: the tree is as it was
    assert builder.last_report["decision"] == "none"
    assert w.view() is made and wide.intersect(w, o, d)[1][0] >= 0
    builder.update(np.asarray(mesh.vertices) * 2.0)  # the binary root box doubles
    assert builder.last_report["decision"] == "rebuild"
    assert np.allclose(builder.bvh.node_uppers.numpy()[0], 2.0 * root_slots_upper, rtol=1e-6)
    n = 1
    outputs = (wp.empty(n, dtype=float, device=device), wp.empty(n, dtype=wp.int32, device=device),
               wp.empty(0, dtype=wp.vec3i, device=device))
    calls = (lambda: w.view(), lambda: wide.intersect(w, o, d), lambda: wide.sah_cost(w), lambda: w.to_numpy(),
             lambda: wide.launch_args(w, wp.array(o, dtype=wp.vec3, device=device),
                                      wp.array(d, dtype=wp.vec3, device=device), 10.0, *outputs))
    for call in calls:
        with pytest.raises(ValueError, match="collapse it again"):
            call()
    fresh = wide.collapse(builder.bvh, 4)
    assert np.allclose(np.array(fresh.view().root_upper), 2.0 * root_slots_upper, rtol=1e-6)
    assert np.array_equal(wide.intersect(fresh, o, d)[1], hw.intersect(builder.bvh, o, d)[1])


def kernels_empty():
    from hlbvh_warp.kernels import wide as wide_kernels

    return wide_kernels.EMPTY_SLOT

def test_wide_rays_on_a_tree_deeper_than_the_stack(device, rng):
    # A caterpillar collapsed at width 16: 15 leaves and one interior child per level, about
    # 40 levels, so rays through the middle would stack more than the traversal's 256 entries.
    v, f = random_soup(rng, 600, scale=0.6)
    w = wide.collapse(caterpillar(v, f, device), 16)
    assert w.depth > 256 // 15
    o, d = random_rays(rng, v, 300)
    t, prim = wide.intersect(w, o, d)
    t_ref, prim_ref = brute_force_closest_hit(v, f, o, d)
    from hlbvh_warp.reference import count_mismatches

    assert count_mismatches(t, prim, t_ref, prim_ref) == 0


def test_small_trees_and_bad_rays(device):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=np.float32)
    one = hw.build(v, np.array([[0, 1, 2]], dtype=np.int32), device=device)
    two = hw.build(v, np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int32), device=device)
    o = np.array([[0.2, 0.2, 5], [0.2, 0.2, 5], [np.nan, 0, 0], [0.2, 0.2, 5]], dtype=np.float32)
    d = np.array([[0, 0, -1], [0, 0, 1], [0, 0, -1], [0, 0, 0]], dtype=np.float32)
    for bvh, first_t in ((one, 5.0), (two, 4.0)):
        for width in (2, 16):
            w = wide.collapse(bvh, width)
            t, prim = wide.intersect(w, o, d)
            assert t[0] == pytest.approx(first_t) and prim[0] >= 0
            assert (prim[1:] == -1).all() and np.isinf(t[1:]).all()
    assert wide.sah_cost(wide.collapse(one, 4)) == pytest.approx(1.0)
    assert wide.sah_cost(wide.collapse(two, 4), 1.0, 1.0) == pytest.approx(metrics.sah_cost(two))


def test_bad_arguments(device):
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float32)
    bvh = hw.build(v, np.array([[0, 1, 2]], dtype=np.int32), device=device)
    for width in (1, 17, 2.5, True, "4"):
        with pytest.raises(ValueError, match="width"):
            wide.collapse(bvh, width)
    with pytest.raises(ValueError, match="takes a Bvh"):
        wide.collapse("tree", 4)
    boxes = hw.build_from_bounds(v, v + 1, device=device)
    w = wide.collapse(boxes, 4)
    with pytest.raises(ValueError, match="mesh"):
        wide.intersect(w, v, v)
    with pytest.raises(ValueError, match="takes a WideBvh"):
        wide.intersect(bvh, v, v)
    with pytest.raises(ValueError, match="mesh"):
        wide.view(w)
    with pytest.raises(ValueError, match="takes a WideBvh"):
        wide.view(bvh)
    with pytest.raises(ValueError, match="t_intersect"):
        wide.sah_cost(w, 1.0, 0.0)
    with pytest.raises(ValueError, match="takes a WideBvh"):
        wide.sah_cost(bvh)


def wide_bench_rows(tmp_path, widths: str) -> list:
    """The rows of a small `bench-wide` run on the generated scene (which must pass)."""
    import json

    from hlbvh_warp import wide_bench

    out = tmp_path / "wide.json"
    code = wide_bench.main(["--scene-tris", "2000", "--widths", widths, "--views", "2", "--side", "16",
                            "--repeats", "1", "--device", "cpu", "--json", str(out)])
    assert code == 0
    return json.loads(out.read_text())["rows"]


def test_bench_wide_rows(tmp_path):
    rows = wide_bench_rows(tmp_path, "4,16")
    for kind in ("primary", "diffuse"):
        ks = {r["k"]: r for r in rows if r["rays"] == kind}
        # Width 2 joins as the baseline; the binary traversal is timed beside it.
        assert set(ks) == {2, 4, 16, "bin"}
        assert ks[2]["speedup"] == 1.0
        assert all(r["disagree"] == 0 and r["mrays_per_s"] > 0 for r in ks.values())
        assert ks[16]["depth"] < ks[4]["depth"] < ks[2]["depth"]
        # Fewer, wider nodes: fewer visited per ray.
        assert ks[16]["n_s"] < ks[4]["n_s"] < ks[2]["n_s"]


def test_bench_wide_rejects_bad_arguments():
    from hlbvh_warp import wide_bench

    for argv in (["--widths", "1"], ["--widths", "4,x"], ["--widths", "32"], ["--method", "nope"], ["--repeats", "0"]):
        with pytest.raises(SystemExit):
            wide_bench.parse_args(argv)


def test_bench_wide_binary_row_counts_as_the_wide_rows(tmp_path):
    """The binary traversal's row counts interior nodes visited and child boxes tested, as the wide
    rows do: over the same tree, front to back, it visits the nodes k = 2 visits (up to ties in
    the order), and a one-triangle tree (a single leaf) has no child box to test."""
    rows = wide_bench_rows(tmp_path, "2")
    for kind in ("primary", "diffuse"):
        ks = {r["k"]: r for r in rows if r["rays"] == kind}
        assert ks["bin"]["n_s"] == pytest.approx(ks[2]["n_s"], rel=0.03)
        assert ks["bin"]["boxes"] == pytest.approx(ks[2]["boxes"], rel=0.03)
    import json

    from hlbvh_warp import wide_bench

    out = tmp_path / "one.json"
    path = tmp_path / "one.obj"
    path.write_text("v 0 0 0\nv 1 0 0\nv 0 1 0.2\nf 1 2 3\n")
    code = wide_bench.main(["--mesh", str(path), "--method", "hlbvh", "--widths", "2", "--views", "2", "--side", "8",
                            "--repeats", "1", "--device", "cpu", "--json", str(out)])
    assert code == 0
    rows = [r for r in json.loads(out.read_text())["rows"] if r["k"] == "bin"]
    assert rows and all(r["n_s"] == 0.0 and r["boxes"] == 0.0 and r["n_t"] > 0 for r in rows)


# ----------------------------------------------------------------- pinned by the mutation audit
def test_stack_fallback_tests_the_whole_range(device):
    """A deck of 600 equal triangles at z = 0, 1, ..., 599 in a caterpillar (the chain holds the
    low ones). A ray going up from between two of them enters the chain first and defers every
    leaf above it, so below the top ~250 levels both traversals run out of stack (64 binary, 256
    wide) and test the current node's whole range [0, m): the triangle just above the origin is
    the last position of that range for one of the rays, and the closest hit of every ray."""
    n = 600
    base = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32)
    v = (base[None] + np.arange(n, dtype=np.float32)[:, None, None] * np.float32([0, 0, 1])).reshape(-1, 3)
    f = np.arange(3 * n, dtype=np.int32).reshape(n, 3)
    bvh = caterpillar(v, f, device)
    o = np.column_stack([np.full(n - 1, 0.25), np.full(n - 1, 0.25), np.arange(n - 1) + 0.5]).astype(np.float32)
    d = np.tile(np.float32([[0, 0, 1]]), (n - 1, 1))
    expected = np.arange(1, n)
    for width in (4, 16):
        t, prim = wide.intersect(wide.collapse(bvh, width), o, d)
        assert np.array_equal(prim, expected) and (t == 0.5).all()
    t, prim = hw.intersect(bvh, o, d)
    assert np.array_equal(prim, expected) and (t == 0.5).all()


@pytest.mark.parametrize("width", [3, 4, 8])
def test_collapse_breaks_area_ties_to_the_earlier_slot(device, width):
    # Equal boxes on a lattice: the median tree's interior children tie in area everywhere, so
    # the collapse must follow its tie rule (the earlier slot) to match the NumPy collapse.
    cells = np.stack(np.meshgrid(np.arange(4), np.arange(4), np.arange(4), indexing="ij"), -1).reshape(-1, 3)
    lo = cells.astype(np.float32) * np.float32(2.0)
    bvh = hw.build_from_bounds(lo, lo + 1, method="median", device=device)
    tree = bvh.to_numpy()
    w = wide.collapse(bvh, width).to_numpy()
    got = sorted(sorted((b, e) for _, b, e, _, _ in slots) for slots in wide_nodes(w, width).values())
    assert got == sorted(numpy_collapse(tree, width).values())


@pytest.mark.parametrize("width", [2, 4])
def test_wide_sah_of_a_zero_area_tree(device, width):
    # Every box one point: each child passes its cost through unscaled (P_hit = 1), so the cost
    # is T1 per child slot of every wide node plus T2 per primitive; at width 2 that is the
    # binary tree's 2 T1 (N - 1) + T2 N.
    n = 13
    pts = np.full((n, 3), 0.5, dtype=np.float32)
    bvh = hw.build_from_bounds(pts, pts, method="median", device=device)
    w = wide.collapse(bvh, width)
    slots = int((w.to_numpy()["slot_child"] != -2).sum())
    assert wide.sah_cost(w, 1.5, 2.0) == pytest.approx(1.5 * slots + 2.0 * n, rel=1e-12)
    if width == 2:
        assert wide.sah_cost(w, 1.5, 2.0) == pytest.approx(2 * 1.5 * (n - 1) + 2.0 * n, rel=1e-12)


def test_a_tiny_direction_gives_the_distance_in_its_units(device):
    # As the binary walk does (traversal.ray_direction_scale): the scaled walk's t scaled back.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, -1], [1, 0, -1], [0, 1, -1]], np.float32)
    f = np.array([[0, 1, 2], [3, 4, 5]], np.int32)
    bvh = hw.build(v, f, device=device)
    o, d = np.array([[0.2, 0.2, 1.0]], np.float32), np.array([[0.0, 0.0, -1e-30]], np.float32)
    expected = 1.0 / np.float64(np.float32(1e-30))  # the plane z = 0 at distance 1
    for width in (2, 4, 8):
        t, prim = wide.intersect(wide.collapse(bvh, width=width), o, d)
        assert prim[0] == 0 and t[0] == pytest.approx(expected, rel=1e-5), width


@pytest.mark.parametrize("scale", [2.0**66, 2.0**-90])
def test_collapse_ranks_areas_at_any_scale(device, scale):
    """An icosphere scaled by 2^66 (coordinates near 7e19) or 2^-90 (near 8e-28): the binary
    tree is the unit sphere's, scaled. The collapse ranked interior children by float32 areas,
    which overflowed to inf (or underflowed to 0) at every node, so every tie went to the earlier
    slot: wide trees deeper (6 -> 9 levels at k = 4) and 9-28% above the unit sphere's wide SAH.
    Scaled by a power of two the areas scale exactly: the wide trees must be the unit sphere's."""
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=3)
    v = np.asarray(mesh.vertices, np.float64)
    f = np.asarray(mesh.faces, np.int32)
    unit = hw.build(v.astype(np.float32), f, method="sweep_sah", device=device)
    scaled = hw.build((v * scale).astype(np.float32), f, method="sweep_sah", device=device)
    a, b = unit.to_numpy(), scaled.to_numpy()
    for name in ("node_left", "node_right", "node_begin", "node_end", "prim_order"):
        assert np.array_equal(a[name], b[name])  # the scene does what the test means
    for width in (4, 8, 16):
        w_unit, w_scaled = wide.collapse(unit, width), wide.collapse(scaled, width)
        got, expected = w_scaled.to_numpy(), w_unit.to_numpy()
        for name in ("slot_child", "slot_begin", "slot_end", "wide_begin", "wide_end"):
            np.testing.assert_array_equal(got[name], expected[name], err_msg=f"{name}, width {width}")
        assert wide.sah_cost(w_scaled) == pytest.approx(wide.sah_cost(w_unit), rel=1e-9)
        assert sorted(numpy_collapse(b, width).values()) == sorted(
            sorted((b_, e_) for _, b_, e_, _, _ in slots) for slots in wide_nodes(got, width).values())
