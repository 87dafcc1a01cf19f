"""A drivable graph through the open space between buildings, for worlds without street centrelines.

The free space (no building, inside the built-up area, at least ``MIN_CLEARANCE_M`` from any
wall) is skeletonised on a 1 m grid; skeleton branches between junctions become edges whose
``width`` is twice the median clearance along them. Short dead-end spurs are pruned.
"""

from __future__ import annotations

import networkx as nx
import numpy as np
from scipy import ndimage as ndi
from shapely.geometry import LineString

from toolkit.errors import CrossviewError

CELL_M = 1.0
MIN_CLEARANCE_M = 4.0
SPUR_M = 25.0
ROAD_PAD_M = 30.0  # with road surfaces: also drive this far outside the buildings' bounding box


def open_space_graph(world, drivable=None) -> nx.Graph:
    """The graph; ``drivable`` (e.g. road surfaces of a city model) restricts the free space."""
    from rasterio.features import rasterize
    from rasterio.transform import Affine
    from shapely.ops import unary_union
    from skimage.morphology import skeletonize

    xmin, ymin, xmax, ymax = world.bounds
    if drivable is not None and not drivable.is_empty:  # roads round the block lie outside its box
        xmin, ymin, xmax, ymax = xmin - ROAD_PAD_M, ymin - ROAD_PAD_M, xmax + ROAD_PAD_M, ymax + ROAD_PAD_M
    w, h = int(np.ceil((xmax - xmin) / CELL_M)), int(np.ceil((ymax - ymin) / CELL_M))
    tr = Affine(CELL_M, 0, xmin, 0, -CELL_M, ymax)
    footprints = [b.footprint for b in world.buildings if not b.footprint.is_empty]
    if not footprints:
        raise CrossviewError(f"synth: {world.name}: no buildings to drive between")
    built = rasterize(((g, 1) for g in footprints), out_shape=(h, w), transform=tr, fill=0, dtype="uint8") > 0
    clearance = ndi.distance_transform_edt(~built) * CELL_M
    if drivable is not None and not drivable.is_empty:
        road = rasterize([(drivable, 1)], out_shape=(h, w), transform=tr, fill=0, dtype="uint8") > 0
        free = road & (clearance >= MIN_CLEARANCE_M / 2)
        opening = 1  # keeps narrow canal-side streets (Delft), which the surfaces already delimit
    else:
        area = unary_union(footprints).convex_hull.buffer(-5.0)
        inside = rasterize([(area, 1)], out_shape=(h, w), transform=tr, fill=0, dtype="uint8") > 0
        free = inside & (clearance >= MIN_CLEARANCE_M)
        opening = 2
    free = ndi.binary_opening(free, iterations=opening)
    skel = skeletonize(free)
    g = _pixel_graph(skel, clearance, xmin, ymax)
    _prune_spurs(g)
    if g.number_of_edges() == 0:
        raise CrossviewError(f"synth: {world.name}: no open space wide enough for a vehicle route")
    g = g.subgraph(max(nx.connected_components(g), key=len)).copy()
    return nx.convert_node_labels_to_integers(g, ordering="sorted")


def _pixel_graph(skel: np.ndarray, clearance: np.ndarray, x0: float, y1: float) -> nx.Graph:
    """Skeleton pixels → graph: clusters of junction pixels and line ends are nodes, the chains
    of two-neighbour pixels between them are edges."""
    eight = np.ones((3, 3), bool)
    deg = ndi.convolve(skel.astype(np.int32), eight.astype(np.int32), mode="constant") - 1
    deg[~skel] = 0
    junction = skel & (deg >= 3)
    clusters, n_clusters = ndi.label(junction, structure=eight)
    node_of = -np.ones(skel.shape, np.int64)
    node_of[junction] = clusters[junction] - 1
    ends = np.argwhere(skel & (deg == 1))
    node_of[ends[:, 0], ends[:, 1]] = n_clusters + np.arange(len(ends))
    H, W = skel.shape

    def xy(r, c):
        return np.array([x0 + (c + 0.5) * CELL_M, y1 - (r + 0.5) * CELL_M])

    g = nx.Graph()
    node_pixels = np.argwhere(node_of >= 0)
    sums = np.zeros((n_clusters + len(ends), 2))
    counts = np.zeros(n_clusters + len(ends))
    ids = node_of[node_pixels[:, 0], node_pixels[:, 1]]
    np.add.at(sums, ids, np.array([xy(r, c) for r, c in node_pixels]))
    np.add.at(counts, ids, 1)
    for k in range(len(counts)):
        g.add_node(k, xy=sums[k] / counts[k])
    visited = np.zeros(skel.shape, bool)
    offsets = [(dr, dc) for dr in (-1, 0, 1) for dc in (-1, 0, 1) if dr or dc]
    for r0, c0 in node_pixels:
        a = int(node_of[r0, c0])
        for dr, dc in offsets:
            r, c = r0 + dr, c0 + dc
            if not (0 <= r < H and 0 <= c < W) or not skel[r, c] or visited[r, c]:
                continue
            if node_of[r, c] == a:
                continue
            path = [(r0, c0), (r, c)]
            while node_of[path[-1]] < 0:
                pr, pc = path[-1]
                visited[pr, pc] = True
                step = None
                for er, ec in offsets:
                    q = (pr + er, pc + ec)
                    if (
                        0 <= q[0] < H
                        and 0 <= q[1] < W
                        and skel[q]
                        and q != path[-2]
                        and not visited[q]
                        and (node_of[q] < 0 or node_of[q] != a or len(path) > 2)
                    ):
                        step = q
                        if node_of[q] >= 0:
                            break
                if step is None:
                    break
                path.append(step)
            b = int(node_of[path[-1]])
            if b < 0 or b == a:
                continue
            pix = np.array(path)
            pts = np.array([xy(pr, pc) for pr, pc in path])
            pts[0], pts[-1] = g.nodes[a]["xy"], g.nodes[b]["xy"]
            line = LineString(pts).simplify(1.0)
            width = 2 * float(np.median(clearance[pix[:, 0], pix[:, 1]]))
            if not g.has_edge(a, b) or g.edges[a, b]["length"] > line.length:
                g.add_edge(
                    a,
                    b,
                    geom=_oriented(line, pts[0], a, b),
                    width=min(width, 30.0),
                    length=max(line.length, 0.5),
                )
    return g


def _oriented(line: LineString, start_xy: np.ndarray, u, v) -> LineString:
    """Geometry from the smaller node key to the larger one (the convention of the street graph)."""
    coords = np.asarray(line.coords)
    starts_at_u = np.linalg.norm(coords[0] - start_xy) < 1e-6
    if (u < v) != starts_at_u:
        coords = coords[::-1]
    return LineString(coords)


def _prune_spurs(g: nx.Graph) -> None:
    for _ in range(3):
        spurs = [
            (u, v)
            for u, v, d in g.edges(data=True)
            if d["length"] < SPUR_M and (g.degree[u] == 1 or g.degree[v] == 1)
        ]
        if not spurs:
            break
        g.remove_edges_from(spurs)
        g.remove_nodes_from([n for n in list(g.nodes) if g.degree[n] == 0])
    # join chains through degree-2 nodes left by pruning into single edges
    for n in [n for n in list(g.nodes) if g.degree[n] == 2]:
        a, b = list(g.neighbors(n))
        if a == b or g.has_edge(a, b):
            continue
        la, lb = g.edges[a, n], g.edges[n, b]
        ca = np.asarray(la["geom"].coords)
        cb = np.asarray(lb["geom"].coords)
        xy_n = g.nodes[n]["xy"]
        ca = ca if np.linalg.norm(ca[-1] - xy_n) < np.linalg.norm(ca[0] - xy_n) else ca[::-1]
        cb = cb if np.linalg.norm(cb[0] - xy_n) < np.linalg.norm(cb[-1] - xy_n) else cb[::-1]
        line = LineString(np.vstack([ca, cb[1:]]))
        width = min(la["width"], lb["width"])
        g.remove_node(n)
        g.add_edge(a, b, geom=_oriented(line, ca[0], a, b), width=width, length=line.length)
