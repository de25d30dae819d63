"""The binary traversal, written once for every binary tree of `BvhNode`s: a mesh's BVH
(bvh.traversal) and a scene's top level over instances (scene.top) each generate theirs
from their own box test and leaf (`make_binary_traversal`).

Near child first with an explicit stack of STACK_SIZE entries (the build's largest depth,
so it cannot overflow): both children's boxes are tested, the nearer is visited next and
the farther pushed with its entry distance; popped nodes that start beyond the closest hit
so far are skipped. An any-hit query ends at the first hit its leaf reports.

The tree plugs in Warp functions that the generated traversal calls directly, compiled in
the caller's module, so they inline as if written in place (as `pool.worker.make_worker`
does for the pool's applications).
"""

# No `from __future__ import annotations`: the generated function's annotations must be the
# tree's types (closure variables), not strings.

from dataclasses import dataclass
from typing import Any

import warp as wp

from ..core.box import INF
from ..core.compile_options import MODULE_OPTIONS
from .node import BvhNode

wp.set_module_options(MODULE_OPTIONS)

STACK_SIZE = 64
NodeStack = wp.types.vector(length=STACK_SIZE, dtype=wp.int32)
DistStack = wp.types.vector(length=STACK_SIZE, dtype=wp.float32)


@dataclass(frozen=True)
class BinaryTree:
    """What a binary tree's traversal plugs in.

    tree: the `@wp.struct` its leaves read (BvhArrays, SceneArrays).
    query: the `@wp.struct` its box and leaf tests take for the ray.
    result: the `@wp.struct` of a hit (`t` inf and nothing hit: see `miss`).
    miss(result: wp.ref): make a zeroed result a miss (in place: initialised by a
        function that returned it, the CPU trace kernel ran 1-2% slower, wide trees
        included, as its code was laid out anew).
    enter(query, lo, hi, tmin, tmax) -> float: the entry distance into the box [lo, hi]
        clipped to [tmin, tmax], or inf where the ray misses it (never missing a box the
        exact ray touches).
    leaf(tree, query, first, count, tmin, tmax, result: wp.ref, any_hit) -> bool: test the
        leaf's items first .. first + count - 1 in [tmin, min(tmax, distance(result))] and
        keep a closer hit in `result`; True when `any_hit` and a hit was found: the
        traversal is done.
    distance(result) -> float: the t of the hit in `result` (inf: none).
    finish(tree, query, tmin, tmax, result, stopped) -> result: what the traversal returns
        (`stopped`: ended by an any hit).
    module: the Warp module to compile the traversal in (the caller's `__name__`).
    name: the generated function's name.
    """

    tree: Any
    query: Any
    result: Any
    miss: Any
    enter: Any
    leaf: Any
    distance: Any
    finish: Any
    module: str
    name: str


def make_binary_traversal(t: BinaryTree):
    """The Warp function (tree, nodes, query, tmin, tmax, any_hit) -> result that traverses
    `nodes` (the tree's `BvhNode` array: inner nodes have children first and first + 1)."""
    Tree, Query, Result = t.tree, t.query, t.result  # noqa: N806 (types, annotated below)
    miss, enter, leaf, distance, finish = t.miss, t.enter, t.leaf, t.distance, t.finish

    def traverse(tree: Tree, nodes: wp.array(dtype=BvhNode), q: Query, tmin: float,
                 tmax: float, any_hit: bool) -> Result:
        hit = Result()
        miss(hit)
        best = tmax
        root = nodes[0]
        if enter(q, root.lo, root.hi, tmin, best) == INF:
            return hit
        stack = NodeStack()
        dists = DistStack()
        sp = int(0)
        node = int(0)
        while True:
            n = nodes[node]
            if n.count > 0:
                if leaf(tree, q, n.first, n.count, tmin, tmax, hit, any_hit):
                    return finish(tree, q, tmin, tmax, hit, True)
                best = wp.min(distance(hit), tmax)
                node = -1
            else:
                left = nodes[n.first]
                right = nodes[n.first + 1]
                tl = enter(q, left.lo, left.hi, tmin, best)
                tr = enter(q, right.lo, right.hi, tmin, best)
                if tl == INF and tr == INF:
                    node = -1
                elif tr == INF:
                    node = n.first
                elif tl == INF:
                    node = n.first + 1
                elif tl <= tr:
                    node = n.first
                    stack[sp] = n.first + 1
                    dists[sp] = tr
                    sp += 1
                else:
                    node = n.first + 1
                    stack[sp] = n.first
                    dists[sp] = tl
                    sp += 1
            while node < 0 and sp > 0:
                sp -= 1
                if dists[sp] <= best:
                    node = stack[sp]
            if node < 0:
                break
        return finish(tree, q, tmin, tmax, hit, False)

    return wp.func(traverse, module=t.module, name=t.name)
