"""SAH-optimized HLBVH (Pantaleoni & Luebke 2010, section 3.3): clusters and the join of the
SAH-built top levels with the Morton treelets below them.

The order of the build is: sort the primitives exactly as HLBVH does; emit the treelets of
every coarse voxel (the cluster) below the voxel bits, with the cluster's root parked in the
arena slots [C - 1, 2C - 1) that the top tree will own; cost every cluster subtree; build the
top tree over the C clusters (kernels/sah.py, weights = cluster costs) in a scratch arena of
2C - 1 nodes; then join:

    final nodes [0, 2C - 1)   the top tree, numbered as built (its leaves are the clusters)
    final nodes [2C - 1, ...)  the treelet nodes, ids unchanged, ranges shifted to where the
                               top tree placed their cluster

so children still come after their parents and the arena still holds 2N - 1 nodes at most.
"""

import warp as wp

# Forward-only kernels: no adjoints to compile.
wp.set_module_options({"enable_backward": False})


@wp.func
def cluster_end(voxel_starts: wp.array(dtype=wp.int32), num_clusters: int, num_prims: int, c: int) -> int:
    """End of cluster c's primitive range: the next cluster's start, or N."""
    if c + 1 < num_clusters:
        return voxel_starts[c + 1]
    return num_prims


@wp.kernel
def coarser_cluster_flags_kernel(
    voxel_starts: wp.array(dtype=wp.int32),
    sorted_codes: wp.array(dtype=wp.int32),
    shift: int,
    flags: wp.array(dtype=wp.int32),
):
    """1 where a voxel starts a voxel of the grid one bit coarser per axis, else 0: merging small
    clusters into coarser ones (``BuildConfig.cluster_min_prims``). An addition of this library's:
    the clusters of Pantaleoni & Luebke 2010 (section 3.3) are the m-bit voxels themselves."""
    # Its code above `shift` differs from the previous voxel's (the sorted order already groups
    # the voxels of a coarser one).
    v = wp.tid()
    flags[v] = 1
    if v > 0:
        if (sorted_codes[voxel_starts[v]] >> shift) == (sorted_codes[voxel_starts[v - 1]] >> shift):
            flags[v] = 0


@wp.kernel
def seed_clusters_kernel(
    num_prims: int,
    num_clusters: int,
    max_leaf_size: int,
    voxel_starts: wp.array(dtype=wp.int32),
    head_to_node: wp.array(dtype=wp.int32),
    head_to_end: wp.array(dtype=wp.int32),
    head_flags: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
    node_count: wp.array(dtype=wp.int32),
):
    """One open treelet segment per cluster (a non-empty coarse voxel, the clusters of Pantaleoni &
    Luebke 2010, section 3.3), owned by its parked root C - 1 + c."""
    # The treelet bookkeeping of kernels/treelets.py: a head flag only while the segment can still
    # split.
    c = wp.tid()
    begin = voxel_starts[c]
    end = cluster_end(voxel_starts, num_clusters, num_prims, c)
    root = num_clusters - 1 + c
    node_begin[root] = begin
    node_end[root] = end
    head_to_node[begin] = root
    head_to_end[begin] = end
    if end - begin > max_leaf_size:
        head_flags[begin] = 1
    else:
        head_flags[begin] = 0
    if c == 0:
        # The top tree's 2C - 1 slots are taken; treelet nodes are numbered after them.
        node_count[0] = 2 * num_clusters - 1


@wp.kernel
def cluster_items_kernel(
    num_prims: int,
    num_clusters: int,
    voxel_starts: wp.array(dtype=wp.int32),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
    node_cost: wp.array(dtype=wp.float64),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    cluster_lowers: wp.array(dtype=wp.vec3),
    cluster_uppers: wp.array(dtype=wp.vec3),
    cluster_cost: wp.array(dtype=wp.float64),
    cluster_left: wp.array(dtype=wp.int32),
    cluster_right: wp.array(dtype=wp.int32),
    cluster_size: wp.array(dtype=wp.int32),
):
    """The items of the top-level SAH sweep: each cluster's box, size, root children and SAH cost,
    the weight that replaces a unit primitive cost (Pantaleoni & Luebke 2010, section 3.3)."""
    # Copy each parked cluster root out before the top tree overwrites its slot.
    c = wp.tid()
    root = num_clusters - 1 + c
    cluster_lowers[c] = node_lowers[root]
    cluster_uppers[c] = node_uppers[root]
    cluster_cost[c] = node_cost[root]
    cluster_left[c] = node_left[root]
    cluster_right[c] = node_right[root]
    cluster_size[c] = cluster_end(voxel_starts, num_clusters, num_prims, c) - voxel_starts[c]


@wp.kernel
def gather_cluster_sizes_kernel(
    cluster_order: wp.array(dtype=wp.int32),
    cluster_size: wp.array(dtype=wp.int32),
    ordered_sizes: wp.array(dtype=wp.int32),
):
    """Cluster sizes in the top tree's cluster order, to be scanned for their new starts (the join
    of Pantaleoni & Luebke 2010, section 3.3)."""
    j = wp.tid()
    ordered_sizes[j] = cluster_size[cluster_order[j]]


@wp.kernel
def cluster_shift_kernel(
    cluster_order: wp.array(dtype=wp.int32),
    ordered_starts: wp.array(dtype=wp.int32),
    voxel_starts: wp.array(dtype=wp.int32),
    cluster_shift: wp.array(dtype=wp.int32),
):
    """How far every primitive of a cluster moves: from its voxel position to its top-tree slot (the
    join of Pantaleoni & Luebke 2010, section 3.3)."""
    j = wp.tid()
    c = cluster_order[j]
    cluster_shift[c] = ordered_starts[j] - voxel_starts[c]


@wp.kernel
def join_top_kernel(
    num_prims: int,
    num_clusters: int,
    top_left: wp.array(dtype=wp.int32),
    top_right: wp.array(dtype=wp.int32),
    top_parent: wp.array(dtype=wp.int32),
    top_begin: wp.array(dtype=wp.int32),
    top_end: wp.array(dtype=wp.int32),
    cluster_order: wp.array(dtype=wp.int32),
    ordered_starts: wp.array(dtype=wp.int32),
    cluster_left: wp.array(dtype=wp.int32),
    cluster_right: wp.array(dtype=wp.int32),
    node_left: wp.array(dtype=wp.int32),
    node_right: wp.array(dtype=wp.int32),
    node_parent: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """The join of the SAH-built top levels with the Morton treelets (Pantaleoni & Luebke 2010,
    section 3.3): top node j becomes final node j, its cluster range turned into a primitive range."""
    j = wp.tid()
    tb = top_begin[j]
    te = top_end[j]
    node_begin[j] = ordered_starts[tb]
    if te < num_clusters:
        node_end[j] = ordered_starts[te]
    else:
        node_end[j] = num_prims
    node_parent[j] = top_parent[j]
    if top_left[j] >= 0:
        node_left[j] = top_left[j]
        node_right[j] = top_right[j]
        return
    # A top leaf is one cluster: it adopts the cluster root's treelet children.
    c = cluster_order[tb]
    left = cluster_left[c]
    right = cluster_right[c]
    node_left[j] = left
    node_right[j] = right
    if left >= 0:
        node_parent[left] = j
        node_parent[right] = j


@wp.kernel
def shift_treelets_kernel(
    first_node: int,
    node_count: wp.array(dtype=wp.int32),
    position_cluster: wp.array(dtype=wp.int32),
    cluster_shift: wp.array(dtype=wp.int32),
    node_begin: wp.array(dtype=wp.int32),
    node_end: wp.array(dtype=wp.int32),
):
    """Move every treelet node's range by its cluster's shift, to where the top tree placed the
    cluster (the join of Pantaleoni & Luebke 2010, section 3.3)."""
    node = wp.tid()
    if node < first_node or node >= node_count[0]:
        return
    c = position_cluster[node_begin[node]]
    node_begin[node] = node_begin[node] + cluster_shift[c]
    node_end[node] = node_end[node] + cluster_shift[c]


@wp.kernel
def scatter_clusters_kernel(
    num_prims: int,
    num_clusters: int,
    voxel_starts: wp.array(dtype=wp.int32),
    cluster_shift: wp.array(dtype=wp.int32),
    sorted_prim_ids: wp.array(dtype=wp.int32),
    prim_order: wp.array(dtype=wp.int32),
    position_cluster: wp.array(dtype=wp.int32),
):
    """Move cluster c's primitives to their top-tree place in prim_order, and record the cluster of
    each of its old positions (the join of Pantaleoni & Luebke 2010, section 3.3)."""
    # One thread per cluster (a few primitives each). The old positions' clusters serve the node
    # shift, so that neither pass searches voxel_starts per element.
    c = wp.tid()
    shift = cluster_shift[c]
    for pos in range(voxel_starts[c], cluster_end(voxel_starts, num_clusters, num_prims, c)):
        prim_order[pos + shift] = sorted_prim_ids[pos]
        position_cluster[pos] = c


@wp.kernel
def top_bounds_sweep_kernel(
    num_top_nodes: int,
    top_left: wp.array(dtype=wp.int32),
    top_right: wp.array(dtype=wp.int32),
    top_begin: wp.array(dtype=wp.int32),
    cluster_order: wp.array(dtype=wp.int32),
    cluster_lowers: wp.array(dtype=wp.vec3),
    cluster_uppers: wp.array(dtype=wp.vec3),
    top_lowers: wp.array(dtype=wp.vec3),
    top_uppers: wp.array(dtype=wp.vec3),
    node_lowers: wp.array(dtype=wp.vec3),
    node_uppers: wp.array(dtype=wp.vec3),
):
    """Boxes of the top tree's nodes (the SAH-built levels of Pantaleoni & Luebke 2010, section 3.3)
    from the cluster boxes, one reverse sweep, into both arenas."""
    # One thread, the top tree's nodes in reverse (children come after their parents), in the
    # top tree's own compact arena: a top leaf is one cluster, whose box was copied out with its
    # cost. Reading those boxes through the joined tree instead went to the cluster roots'
    # children, scattered over the 2N - 1 node arena: 1.1 ms of cache misses on the armadillo's
    # 11,771 clusters against 0.1 ms here.
    j = num_top_nodes - 1
    while j >= 0:
        left = top_left[j]
        if left < 0:
            c = cluster_order[top_begin[j]]
            lower = cluster_lowers[c]
            upper = cluster_uppers[c]
        else:
            right = top_right[j]
            lower = wp.min(top_lowers[left], top_lowers[right])
            upper = wp.max(top_uppers[left], top_uppers[right])
        top_lowers[j] = lower
        top_uppers[j] = upper
        node_lowers[j] = lower
        node_uppers[j] = upper
        j -= 1
