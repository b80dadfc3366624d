"""Linear solves of the Newton iteration: (K_t + eps M) ddu = R.

Owns the three paths behind :func:`linear_solve`, chosen by
``model.linear_solver`` (static): "dense" (LU of the assembled matrix, Cholesky where
it is symmetric and large: :func:`solve_dense`; in float32 refined in float64,
:func:`refined_solve`), "sparse" (SuiteSparse's CHOLMOD or KLU
inside the program, :func:`_solve_sparse`) and "cg" (matrix-free preconditioned
conjugate gradients, :func:`solve_cg`); and the assembly they share
(:func:`stiffness_blocks`, :func:`assemble_dense` and :func:`dense_of`,
:func:`host_matrix`), with what a sub-step's sparse matrices share formed once a
sub-step (:func:`sparse_pattern`).

Data flow: takes the rank-one terms of :mod:`jaxdem.core._springs` and the
gather/scatter of :mod:`jaxdem.core.kinematics`; used by the Newton iteration
(:mod:`jaxdem.core._substep`) and, for its assembly, by the sensitivity solve
(:mod:`jaxdem.core.sensitivities`).
"""

from __future__ import annotations

import contextlib
import functools
import threading
import time
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxdem.core._springs import Sub, bolt_term_blocks, n_bolt_terms, with_coupling
from jaxdem.core.kinematics import gather_pairs, scatter_pairs
from jaxdem.core.state import Model


def linear_solve(model: Model, sub: Sub, terms, R, rtol=None, active=True, symmetric=True,
                 coupling=None, pattern=None):
    """(K_t + eps M)^-1 R (N, D) by the model's linear solver (``model.linear_solver``).

    ``terms`` (a, b, B, k) are the symmetric rank-one terms of K_t
    (:func:`jaxdem.core._springs.stiffness_terms`); ``coupling`` (a, b, L, Rt, k),
    the slip coupling (:func:`jaxdem.core._springs.slip_coupling`), makes it
    unsymmetric on the direct paths ("cg" takes the symmetric part alone). ``rtol``
    is the relative residual at which CG stops (:func:`solve_cg`); ``symmetric`` (a
    traced bool: False where the coupling is on) is for the direct paths
    (:func:`_solve_sparse`, :func:`solve_dense`), ``active`` for the sparse one. The
    choice is static: only the chosen path is traced. ``pattern``: what the sparse path's
    matrices of this sub-step share (:func:`sparse_pattern`), where the caller formed it
    once.
    """
    if model.linear_solver == "cg":
        return solve_cg(model, sub, terms, R, rtol)
    if model.linear_solver == "sparse":
        return _solve_sparse(model, sub, terms, R, active, symmetric, coupling, pattern)
    return solve_dense(model, sub, terms, R, symmetric, coupling)


def _unsymmetric(sub: Sub, terms, coupling):
    """The symmetric terms (a, b, B, k) with the coupling group, if any, as (a, b, L, Rt, k)."""
    if coupling is None:
        a, b, B, k = terms
        return a, b, B, B, k
    return with_coupling(terms, coupling, sub.geo.a.shape[0])


def stiffness_blocks(model: Model, sub: Sub, a, b, L, Rt, k, diag, paired=None):
    """sum_m k_m L_m R_m^T + blockdiag(Kc) + diag(diag) as (D, D) blocks: (rows, cols, blocks).

    Block (rows[i], cols[i]) of the (N, N) block matrix gets ``blocks[i]``
    (summed where several land on one: :func:`assemble_dense` scatters them,
    :func:`host_matrix` hands them to SciPy). The blocks are laid out as the
    (M', ...) off-diagonal blocks (first, second) of the pairs and bolts, then
    their (second, first), then the N diagonal blocks, each summed over every
    pair and bolt of its block (the last N). L and Rt (M, 2 D) are the left
    and right rows of each term over the DOFs of its blocks (a, b); L = Rt for
    the symmetric iteration matrix. The terms start with whole groups of
    spring slots (P pairs x 2 sides x V vertices, in the order of
    ``sub.geo``) and end with the bolts. The 2 V slots of a pair share its two
    blocks, so they are summed into one (2 D, 2 D) block per pair first (a
    dense contraction): 2 V times fewer blocks than one per slot. Packed slots
    (``sub.packed``) are summed into the blocks of their pairs the same way, so
    the matrix has the same pattern either way. ``paired``: the slots' rows L = Rt
    of a symmetric matrix whose groups are the sub-step's rows Bn and Bs
    (:func:`jaxdem.core._springs.stiffness_terms`), laid out by pair once a sub-step
    (:func:`pair_rows`, :func:`sparse_pattern`): only k is then laid out here.
    """
    N, D = model.n_blocks, model.ndof
    S = sub.geo.a.shape[0]
    T = (k.shape[0] - n_bolt_terms(model)) // S
    grid, rows, cols = _block_layout(model, sub, a, b, T)
    # Sum over the slots of each pair of k L R^T: elementwise products and a sum written
    # out (XLA fuses them into one loop), not P tiny matrix products, nor a scatter of
    # each slot's (2 D, 2 D) product: on seed example 2's 36,864 packed places that
    # product alone is 42 MB, and its segment sum took 23 ms against 4 (of a Newton
    # iteration's 70); XLA's CPU reduction over an axis of a (T, ...) product also took
    # 40 times as long (10 ms against 0.24 on the demo tunnel).
    if paired is None:
        kL, R = pair_rows(model, sub, k[:, None] * L, T), pair_rows(model, sub, Rt, T)
    else:
        # The same products k L, of the values laid out: bit for bit the same blocks.
        kL, R = _by_pair(model, sub, k[:T * S].reshape(T, S))[..., None] * paired, paired
    Kp = sum(kL[t, :, i, :, None] * R[t, :, i, None, :]
             for t in range(T) for i in range(grid.shape[1]))
    # The rest (bolts): a (2 D, 2 D) block per term.
    L, Rt, k = L[T * S:], Rt[T * S:], k[T * S:]
    Kp = jnp.concatenate([Kp, k[:, None, None] * L[:, :, None] * Rt[:, None, :]])
    Kp = Kp.reshape(-1, 2, D, 2, D)
    M = Kp.shape[0]
    first, second = rows[:M], rows[M:2 * M]
    # Each block's own (diagonal) block, summed here over its pairs and bolts (a segment
    # sum, 0.2 ms on seed example 2), so that the sparse solver gets one triplet per
    # entry there rather than one per pair: it sorts its triplets for every new pattern,
    # and on seed example 2 that sort of 1.8 million triplets cost 115 ms (CHOLMOD) and
    # 190 ms (KLU) a sub-step, more than the factorisation.
    own = jax.ops.segment_sum(jnp.concatenate([Kp[:, 0, :, 0], Kp[:, 1, :, 1]]),
                              jnp.concatenate([first, second]), N)
    own = own + (diag.reshape(N, D)[:, :, None] * jnp.eye(D, dtype=diag.dtype)).astype(own.dtype)
    if sub.Kc is not None:
        own = own + sub.Kc.astype(own.dtype)
    blocks = jnp.concatenate([Kp[:, 0, :, 1], Kp[:, 1, :, 0], own])
    return rows, cols, blocks


def _block_layout(model: Model, sub: Sub, a, b, T: int):
    """Where :func:`stiffness_blocks` puts its blocks: (grid, rows, cols).

    ``grid`` (pairs, m) holds each pair's slots (:func:`_grid`); ``rows`` and ``cols``
    the block row and column of each block: (first, second) of the pairs and bolts, then
    (second, first), then the N diagonal blocks. ``a``, ``b``: the blocks of the terms (T
    groups of the S slots, then the bolts'). They depend on the sub-step alone
    (:func:`sparse_pattern`).
    """
    N = model.n_blocks
    S = sub.geo.a.shape[0]
    V = model.n_vertices
    grid = _grid(model, sub)[0]
    if sub.packed is None:
        first, second = a[:S:2 * V], b[:S:2 * V]
    else:
        first, second = sub.packed.first, sub.packed.second
    touching = jnp.any(jnp.append(sub.geo.active, False)[grid], axis=1)
    # A candidate pair that does not touch couples nothing: its (zero) blocks go to its
    # first block's diagonal, so that the matrix's pattern holds the touching pairs
    # alone (most candidate pairs do not touch: on seed example 2, 4,300 of 8,678; a
    # sparse factorisation pays for every entry of the pattern).
    second = jnp.where(touching, second, first)
    first, second = jnp.concatenate([first, a[T * S:]]), jnp.concatenate([second, b[T * S:]])
    rows = jnp.concatenate([first, second, jnp.arange(N)])
    cols = jnp.concatenate([second, first, jnp.arange(N)])
    return grid, rows, cols


def _grid(model: Model, sub: Sub):
    """(grid, slot): each pair's slots side by side, (pairs, m), index S where none (the
    packed ones, :func:`jaxdem.core._substep.pack_slots`, or all 2 V of each candidate
    pair), and their places in the slot list."""
    if sub.packed is not None:
        return sub.packed.grid, sub.packed.slot
    S = sub.geo.a.shape[0]
    V = model.n_vertices
    return jnp.arange(S).reshape(S // (2 * V), 2 * V), jnp.arange(S)


def _by_pair(model: Model, sub: Sub, x):
    """(T, S, ...) values of the slots -> (T, pairs, m, ...) laid out by :func:`_grid`,
    zero at the empty places."""
    grid = _grid(model, sub)[0]
    return jnp.concatenate([x, jnp.zeros(x.shape[:1] + (1,) + x.shape[2:], x.dtype)],
                           axis=1)[:, grid]


def pair_rows(model: Model, sub: Sub, x, T: int):
    """(T S, 2 D) rows of T groups of the slots -> (T, pairs, m, 2 D): each pair's slots
    (:func:`_grid`), their rows ordered (first block, second block) of the pair (side 1's
    halves swap), zero rows for the empty places."""
    S = sub.geo.a.shape[0]
    D, V = model.ndof, model.n_vertices
    side1 = ((_grid(model, sub)[1] // V) % 2 == 1)[None, :, None]
    x = x[:T * S].reshape(T, S, 2 * D)
    return _by_pair(model, sub, jnp.where(side1, jnp.concatenate([x[..., D:], x[..., :D]],
                                                                 axis=-1), x))


class SparsePattern(NamedTuple):
    """What every iteration matrix of a sub-step on the sparse path shares
    (:func:`sparse_pattern`)."""

    upper: tuple  # (Ai, Aj) of the triplets of its upper triangle (:func:`coo_of_blocks`)
    whole: tuple  # (Ai, Aj) of the triplets of the whole matrix
    paired: jax.Array  # (2, pairs, m, 2 D): the slots' rows Bn, Bs laid out by pair


def sparse_pattern(model: Model, sub: Sub) -> SparsePattern:
    """What a sub-step's iteration matrices share on the sparse path, formed once a
    sub-step rather than once an iteration: the triplets' indices, and the rows of the
    springs' terms laid out by pair.

    The blocks' places depend on the sub-step's slots and bolts alone
    (:func:`_block_layout`), not on the springs' states, nor on the slip coupling (its
    terms are the slots' own: summed into the same pairs' blocks); the rows of the
    secant's and the slip tangent's symmetric part are the sub-step's Bn and Bs
    (:func:`jaxdem.core._springs.stiffness_terms`), their stiffness alone changes. Formed
    in every iteration, the indices were two loops over the triplets (on seed example 2,
    267,264 of them, 0.55-0.6 ms each) and the rows' layout 1 ms of the 2 ms in which the
    pairs' blocks were summed.
    """
    a, b = sub.geo.a, sub.geo.b
    if model.n_bolts:
        ba, bb = bolt_term_blocks(model, sub.bolt)
        a, b = jnp.concatenate([a, ba]), jnp.concatenate([b, bb])
    _, rows, cols = _block_layout(model, sub, a, b, 1)
    return SparsePattern(coo_index(model, rows, cols, upper=True), coo_index(model, rows, cols),
                         pair_rows(model, sub, jnp.concatenate([sub.Bn, sub.Bs]), 2))


def blocks_times(model: Model, rows, cols, blocks, x):
    """The block matrix of :func:`stiffness_blocks` times x, (n,) or (n, p), n = D N: each
    (D, D) block times its column block of x, summed into its row block."""
    N, D = model.n_blocks, model.ndof
    xb = x.reshape((N, D) + x.shape[1:])[cols]
    return jax.ops.segment_sum(jnp.einsum("kij,kj...->ki...", blocks, xb), rows,
                               N).reshape(x.shape)


def assemble_dense(model: Model, sub: Sub, a, b, L, Rt, k, diag):
    """sum_m k_m L_m R_m^T + blockdiag(Kc) + diag(diag) as a dense (D N, D N) matrix.

    Scatters the (D, D) blocks of :func:`stiffness_blocks` into K laid out as (N, D,
    N, D): whole windows, far cheaper than one scattered scalar per entry, and
    a batch of them (vmap) stays cache-friendly.
    """
    return dense_of(model, *stiffness_blocks(model, sub, a, b, L, Rt, k, diag))


def dense_of(model: Model, rows, cols, blocks):
    """The block matrix of :func:`stiffness_blocks` as a dense (D N, D N) matrix."""
    N, D = model.n_blocks, model.ndof
    K4 = jnp.zeros((N, D, N, D), blocks.dtype).at[rows, :, cols, :].add(blocks)
    return K4.reshape(N * D, N * D)


def pseudo_mass_diagonal(model: Model, sub: Sub):
    """The (D N,) diagonal added to K: eps M on the free blocks' unknowns, 1 elsewhere (a
    fixed or dead block's rows then solve to a zero step)."""
    return jnp.where(jnp.repeat(sub.free, model.ndof), model.pseudo_mass.reshape(-1), 1.0)


def _lu_alone(model: Model, dtype) -> bool:
    """Whether the direct paths factorise by LU whatever the symmetry (static): only a
    matrix positive definite beyond rounding may go to Cholesky, which is a float64 one
    (eps M, a millionth of the stiffness, is far above its rounding; float32 rounding
    broke seed example 2's for CHOLMOD) of springs and cells alone (a bolt's geometric
    stiffness F H can be indefinite in rotation), in a single solve (under vmap, a batch's
    ``model.lanes``, a cond would run both factorisations)."""
    return model.lanes is not None or bool(model.n_bolts) or dtype != jnp.float64


def solve_dense(model: Model, sub: Sub, terms, R, symmetric=True, coupling=None):
    """(K_t + eps M)^-1 R on the assembled (D N, D N) matrix.

    ``terms`` (a, b, B, k), ``symmetric`` and ``coupling`` as :func:`linear_solve` takes
    them: K is unsymmetric where the slip coupling is on, and then factorised by LU.
    Where it is symmetric and has more than :data:`DENSE_CHOLESKY_ABOVE` unknowns (the
    dense path of a GPU, which "auto" takes up to 32,000 unknowns), by Cholesky: n^3 / 3
    operations against LU's 2 n^3 / 3 (seed example 2's 7,680 unknowns on the 2-core
    CPU: 2.4 s against 3.4), LU where its answer is not finite (a matrix not positive
    definite). LU alone where :func:`_lu_alone` says so, as on the sparse path (in a
    batch also because two batched LAPACK calls that may run at once can deadlock XLA's
    CPU thread pool, see :func:`jaxdem.batch._one_per_device`; LU costs about 7% of a
    batched sweep's time, measured on the 52-block benchmark tunnel).
    """
    diag = pseudo_mass_diagonal(model, sub)
    rhs = R.reshape(-1)

    def by_lu():
        rows, cols, blocks = stiffness_blocks(model, sub, *_unsymmetric(sub, terms, coupling),
                                              diag)
        K = dense_of(model, rows, cols, blocks)
        if K.dtype == jnp.float64:
            return jnp.linalg.solve(K, rhs)
        wide = blocks.astype(jnp.float64)
        return refined_solve(K, rhs, lambda x: blocks_times(model, rows, cols, wide, x))

    if model.n_blocks * model.ndof <= DENSE_CHOLESKY_ABOVE or _lu_alone(model, R.dtype):
        return by_lu().reshape(R.shape)

    def by_cholesky():  # where symmetric the coupling's terms are zero: K is the terms'
        a, b, B, k = terms
        K = assemble_dense(model, sub, a, b, B, B, k, diag)
        return jax.scipy.linalg.cho_solve(jax.scipy.linalg.cho_factor(K), rhs)

    # NaN stands for "not solved" (the unsymmetric matrix, or Cholesky's factor of one
    # that is not positive definite): one LU in the program for both.
    x = jax.lax.cond(jnp.asarray(symmetric), by_cholesky, lambda: jnp.full_like(rhs, jnp.nan))
    x = jax.lax.cond(jnp.all(jnp.isfinite(x)), lambda: x, by_lu)
    return x.reshape(R.shape)


#: Corrections of :func:`refined_solve` (float32 dense solves).
REFINE_STEPS = 2


def refined_solve(K, rhs, times=None, steps: int = REFINE_STEPS):
    """K^-1 rhs for a float32 K: its LU in float32, then ``steps`` corrections by the same
    factors of the residual formed in float64 (mixed-precision iterative refinement), the
    answer in float32. ``times(x)``: the matrix times a float64 x, in float64 (the
    dense path's from the pairs' blocks: no float64 copy of K, 8 GB at a GPU's 32,000
    unknowns); K.astype(float64) @ x where None.

    The iteration matrix joins stiff springs (kn, a million times eps M) to blocks that
    only eps M holds (a block falling free, a pair of them): a float32 LU alone leaves
    an error of cond(K) eps relative to the step, most of it in the soft modes, a rigid
    turn of two blocks falling side by side of 1e-3 rad a sub-step (tests/
    test_hard_cases.py, blocks that fall together). Each correction divides the error by
    about 1 / (cond(K) eps): after two, the answer of float32's K to its rounding (the
    same pair turns by 6e-9 rad in all, as with a float64 solve), for two triangular
    solves (n^2, against the LU's n^3) and a float64 product a correction.
    """
    if times is None:
        times = lambda x: K.astype(jnp.float64) @ x  # noqa: E731
    factors = jax.scipy.linalg.lu_factor(K)
    b64 = rhs.astype(jnp.float64)
    x = jax.scipy.linalg.lu_solve(factors, rhs).astype(jnp.float64)
    for _ in range(steps):
        r = b64 - times(x)
        x = x + jax.scipy.linalg.lu_solve(factors, r.astype(K.dtype)).astype(jnp.float64)
    return x.astype(rhs.dtype)


#: Unknowns above which :func:`solve_dense` factorises a symmetric matrix by Cholesky:
#: more than any dense choice of a CPU's "auto" (600), so that those programs, and their
#: answers, stay as they were; every dense solve of a GPU but the smallest scenes'.
DENSE_CHOLESKY_ABOVE = 600


def host_matrix(rows, cols, blocks, n: int):
    """The block matrix of :func:`stiffness_blocks` as an (n, n) SciPy CSC matrix (host arrays).

    Blocks that are all zero (unused pairs of the padded list) are left out.
    Assembling from the pairs' blocks, summed on the device, rather than from
    one outer product per spring on the host, cut the demo's host assembly
    from 9 ms to about 2 ms an iteration.
    """
    import scipy.sparse

    rows, cols, blocks = np.asarray(rows), np.asarray(cols), np.asarray(blocks)
    D = blocks.shape[1]
    keep = np.any(blocks != 0, axis=(1, 2))
    rows, cols, blocks = rows[keep], cols[keep], blocks[keep]
    r = np.broadcast_to(D * rows[:, None, None] + np.arange(D)[:, None], blocks.shape)
    c = np.broadcast_to(D * cols[:, None, None] + np.arange(D)[None, :], blocks.shape)
    return scipy.sparse.csc_matrix((blocks.ravel(), (r.ravel(), c.ravel())), shape=(n, n))


def _host_sparse_solve(rows, cols, blocks, rhs, active=True, symmetric=True):
    """Assemble K from its (D, D) blocks (:func:`stiffness_blocks`) on the host and solve K x = rhs.

    The fallback of :func:`_solve_sparse` where sparsax is not installed: SciPy's SuperLU
    (minimum-degree ordering of K + K^T) through a host callback, which JAX cannot store
    in its compilation cache. ``rhs`` is (n,) or (n, p). ``active`` False returns zeros
    at once (a finished batch member).
    """
    import scipy.sparse.linalg

    if not bool(np.asarray(active)):
        return np.zeros_like(np.asarray(rhs))
    symmetric = bool(np.asarray(symmetric))
    rhs = np.asarray(rhs)
    K = host_matrix(rows, cols, blocks, rhs.shape[0])
    if symmetric:
        # K is symmetric positive definite: symmetric ordering, no pivoting
        # (ten times faster than SuperLU's default partial pivoting).
        lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                      options=dict(SymmetricMode=True))
    else:
        lu = scipy.sparse.linalg.splu(K, permc_spec="MMD_AT_PLUS_A")
    return lu.solve(rhs).astype(rhs.dtype)


def _sparsax():
    """The sparsax module (SuiteSparse's CHOLMOD and KLU as XLA FFI calls), or None."""
    try:
        import sparsax
    except ImportError:  # a platform without its wheel: the SciPy callback instead
        return None
    return sparsax


def release_factorisations() -> None:
    """Free what sparsax keeps from one solve to the next: the analysis of every sparsity
    pattern it has seen, and their numeric factors.

    sparsax keeps them for the life of the process, and a new pattern comes nearly every
    sub-step, as contacts open and close (6 MB a pattern on a 40 x 40 grid's 5,376
    unknowns, 15-18 on seed example 3's 4,608 in meshed rock, with up to 32 KLU factors
    a pattern), so a long analysis of a large scene would grow by that much a sub-step.
    The host frees them while an increment runs and after it
    (:func:`bounded_factorisations`). Safe while other threads solve: every CHOLMOD call
    holds sparsax's lock for its whole work and no factor token of jaxdem outlives its
    call (:func:`_slip_gmres`), and KLU's patterns are reference-counted; a solve whose
    pattern went analyses it again and factorises again, to the same numbers.
    """
    sparsax = _sparsax()
    if sparsax is not None:
        sparsax.clear_cache()


#: :func:`bounded_factorisations`: the patterns sparsax may hold while an increment runs
#: (more, and they are all freed), and how often that is looked at (s).
MAX_PATTERNS = 4
WATCH_EVERY_S = 0.2

_RUNNING = {"count": 0, "watcher": None}  # increments in flight and the watching thread
_RUNNING_LOCK = threading.Lock()


@contextlib.contextmanager
def bounded_factorisations():
    """Hold sparsax's memory to a few patterns while the body runs (an increment's program,
    up to its result), and free it all when the body ends.

    An increment is one program, and a pattern comes nearly every geometry update: a
    failing step of seed example 3 (40 geometry updates) went from 0.7 to 1.2 GB. A
    thread of its own (one for all the increments in flight, such as a sweep's workers)
    looks every :data:`WATCH_EVERY_S` seconds and frees them all
    (:func:`release_factorisations`) where there are more than :data:`MAX_PATTERNS`; the
    pattern in use is then analysed and factorised again, once.
    """
    sparsax = _sparsax()
    if sparsax is None:
        yield
        return
    with _RUNNING_LOCK:
        _RUNNING["count"] += 1
        if _RUNNING["watcher"] is None:
            _RUNNING["watcher"] = threading.Thread(target=_watch, args=(sparsax,), daemon=True,
                                                   name="jaxdem-sparsax-bound")
            _RUNNING["watcher"].start()
    try:
        yield
    finally:
        with _RUNNING_LOCK:
            _RUNNING["count"] -= 1
        release_factorisations()


def _watch(sparsax) -> None:
    """The thread of :func:`bounded_factorisations`: it ends once no increment runs."""
    while True:
        with _RUNNING_LOCK:
            if _RUNNING["count"] == 0:
                _RUNNING["watcher"] = None
                return
        if sparsax.cache_size() > MAX_PATTERNS:
            release_factorisations()
        time.sleep(WATCH_EVERY_S)


def _solve_sparse(model: Model, sub: Sub, terms, R, active=True, symmetric=True, coupling=None,
                  pattern=None):
    """(K_t + eps M)^-1 R by a sparse direct solve inside the compiled program.

    SuiteSparse through sparsax's XLA FFI calls, so that the program is one XLA
    executable (stored and loaded like any other; a vmapped batch's members solved one
    after another, each with its own pattern: :func:`_lu_each_lane`): CHOLMOD
    (supernodal Cholesky) where the iteration matrix is symmetric positive definite
    beyond rounding; for the slip tangent (``symmetric`` False, the
    symmetric ``terms`` plus the ``coupling``) GMRES preconditioned by CHOLMOD's factor
    of its symmetric part (:func:`_slip_gmres`), KLU (LU) of the whole where that does
    not converge or the scene has at most :data:`SLIP_LU_UP_TO` unknowns; KLU alone for
    a scene with bolts (their geometric stiffness), float32, a batch (where a choice
    would run both). On the 60 x 60 and 100 x 100 block
    grids of BENCHMARKS.md ("Sparse solve inside XLA") CHOLMOD factorised twice as
    fast as SciPy's SuperLU and KLU two to three times slower. Fill-in of a 2D contact
    graph is mild, so cost and memory grow about linearly with the number of blocks,
    and a direct solve does not slow down near a mechanism as an iterative one does.
    The springs of each pair are summed into (D, D) blocks on the device
    (:func:`stiffness_blocks`) and handed over as COO triplets (duplicates summed,
    the blocks of unused pairs zero); float32 scenes are solved in float64.
    Without sparsax, SciPy's SuperLU on the host (:func:`_host_sparse_solve`).
    ``pattern``: the triplets' indices and the springs' rows laid out by pair
    (:func:`sparse_pattern`), else formed here.
    """
    diag = pseudo_mass_diagonal(model, sub)
    up, both, paired = (None, None, None) if pattern is None else pattern
    rhs = R.reshape(-1)
    sparsax = _sparsax()

    def whole():  # the blocks of K, coupling included
        return stiffness_blocks(model, sub, *_unsymmetric(sub, terms, coupling), diag)

    if sparsax is None:
        rows, cols, blocks = whole()
        x = jax.pure_callback(_host_sparse_solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype),
                              rows, cols, blocks, rhs, jnp.asarray(active),
                              jnp.asarray(symmetric), vmap_method="sequential")
        return x.reshape(R.shape)
    b64 = rhs.astype(jnp.float64)
    if model.lanes is not None:
        x = _lu_each_lane(sparsax)(jnp.asarray(active), *coo_of_blocks(model, *whole(), index=both),
                                   b64)
        return x.astype(R.dtype).reshape(R.shape)
    # CHOLMOD stops the whole program where its matrix is not positive definite, so it
    # only gets what :func:`_lu_alone` lets through.
    if _lu_alone(model, R.dtype):
        x = sparsax.lu_solve(*coo_of_blocks(model, *whole(), index=both), b64)
        return x.astype(R.dtype).reshape(R.shape)
    if coupling is not None and model.n_blocks * model.ndof <= SLIP_LU_UP_TO:
        # One assembly for both: where symmetric the coupling's terms are zero, and K's
        # blocks are the symmetric part's to the last bit (zeros added last).
        blocks = whole()
        x = jax.lax.cond(jnp.asarray(symmetric),
                         lambda: sparsax.solve(*coo_of_blocks(model, *blocks, upper=True,
                                                              index=up), b64),
                         lambda: sparsax.lu_solve(*coo_of_blocks(model, *blocks, index=both), b64))
        return x.astype(R.dtype).reshape(R.shape)
    a, b, B, k = terms

    def symmetric_part():  # K_s's blocks and the triplets of its upper triangle
        sym = stiffness_blocks(model, sub, a, b, B, B, k, diag, paired)
        return sym, coo_of_blocks(model, *sym, upper=True, index=up)

    def cholesky():
        # The triplets alone, formed here: formed before the choice, the secant also
        # formed the block list that only GMRES reads (XLA formed the triplets' values
        # from the springs again beside it: one loop over the pairs' blocks more, 1.2-1.5
        # ms an iteration on seed example 2).
        return sparsax.solve(*symmetric_part()[1], b64)

    if coupling is None:
        x = cholesky()
    else:
        def slip():
            sym, upper = symmetric_part()
            return _slip_gmres(model, sparsax, sym, upper, coupling, b64,
                               lambda: sparsax.lu_solve(*coo_of_blocks(model, *whole(), index=both),
                                                        b64))

        x = jax.lax.cond(jnp.asarray(symmetric), cholesky, slip)
    return x.astype(R.dtype).reshape(R.shape)


@functools.cache
def _lu_each_lane(sparsax):
    """``lu(active, Ai, Aj, Ax, b)``: sparsax's KLU solve of A x = b, and under a batch's
    vmap each sample's own, one after another, skipped (x = 0) where ``active`` is False.

    sparsax's own rule for vmap solves the whole batch in one native call with the
    sparsity pattern of its first member (its contract: the pattern is shared, only the
    values vary; "passing them silently uses the first"). The samples of a batch have
    their own contacts, so their own patterns: solved with the first sample's, a sample
    whose contacts differ got the wrong step (the loose-roof tunnel's sweep in chunks of
    four on the sparse path: three mechanisms where each sample's own solve converges,
    tests/test_batch.py). Here each sample's matrix is factorised with its own pattern (its
    analysis cached by sparsax as any pattern's), and a sample whose Newton loop has ended
    costs nothing.
    """
    @jax.custom_batching.custom_vmap
    def lu(active, Ai, Aj, Ax, b):
        return sparsax.lu_solve(Ai, Aj, Ax, b)

    @lu.def_vmap
    def _each(axis_size, in_batched, *args):
        args = tuple(x if batched else jnp.broadcast_to(x, (axis_size,) + x.shape)
                     for x, batched in zip(args, in_batched, strict=True))

        def one(member):
            active, Ai, Aj, Ax, b = member
            return jax.lax.cond(active, lambda: sparsax.lu_solve(Ai, Aj, Ax, b),
                                lambda: jnp.zeros_like(b))

        return jax.lax.map(one, args), True

    return lu


#: The slip tangent's GMRES (:func:`_slip_gmres`): at most this many iterations (the
#: Krylov space's dimension, no restart), and the relative residual it stops at.
GMRES_MAX = 40
GMRES_RTOL = 1e-11
#: The slip tangent's GMRES answer is also taken where its residual is within this many
#: round-offs of |K| |x| + |b| (a normwise backward error: what any solve, KLU's too,
#: can reach in the scene's floating point).
BACKWARD_ROUND_OFFS = 16
#: Unknowns up to which the slip tangent is factorised by KLU whole rather than solved by
#: GMRES (:func:`_solve_sparse`): there one costs what the other does (a slip solve of a
#: grid-like matrix with a tenth of its springs coupled, new values each call: 3.2 ms
#: against 3.7 at 768 unknowns, 11.8 against 11.2 at 2,028), and without GMRES the
#: program is smaller (seed example 4 wet's increment compiled in 4.2-4.7 s against
#: 4.8-4.9, BENCHMARKS.md, "Thirty-fourth session"). Above it, meshed rock's LU fills in
#: more than a Cholesky factor: on seed example 2, 95-140 ms an LU against 31 ms a
#: Cholesky factor and 2 a solve.
SLIP_LU_UP_TO = 2000


def _slip_gmres(model: Model, sparsax, sym, upper, coupling, b, fallback):
    """K^-1 b for the slip tangent K = K_s + C by GMRES preconditioned with K_s's Cholesky factor.

    K_s (``sym``: the blocks of :func:`stiffness_blocks`; ``upper``: its upper triangle
    as COO triplets, :func:`coo_of_blocks`) is the tangent without the
    slip coupling, symmetric positive definite; C (``coupling``, rank-one terms (a, b,
    L, Rt, k): -(d fs / d fn) kn Bs Bn^T of each slipping slot,
    :func:`jaxdem.core._springs.slip_coupling`) has rank at most the number of
    slipping slots, so K K_s^-1 = I + C K_s^-1 is the identity but for a low-rank part
    and GMRES ends in a few iterations (at most that rank + 1 in exact arithmetic;
    about 5 on seed example 2). CHOLMOD's factor of K_s (its pattern's analysis
    shared with the sub-step's secant iterations) and its triangular solves cost a
    fraction of KLU's factorisation of K: on seed example 2, 31 ms a factor and 2 a
    solve, against 95-140 ms an LU. The preconditioner is sparsax's ``solve`` on K_s's
    triplets: it factorises on the first call and finds the same values in the others
    (a comparison of the triplets, under a millisecond at 4,608 unknowns). Not its
    factor tokens (``factor`` / ``solve_factor``): sparsax 0.9 keeps a copy of every
    factor a token was made for until its cache is cleared (about 1 GB after seed
    example 3's run). Where GMRES does not reach :data:`GMRES_RTOL` in
    :data:`GMRES_MAX` iterations, nor a residual at the rounding of K x
    (:data:`BACKWARD_ROUND_OFFS`; both checked on the true residual), ``fallback`` (KLU on
    K) answers instead.
    """
    N, D = model.n_blocks, model.ndof
    ca, cb, cL, cR, ck = coupling

    def times(x, f=lambda v: v):  # K x, or with f = abs |K| x: the size of its terms
        coupled = f(ck) * jnp.sum(f(cR) * gather_pairs(x.reshape(N, D), ca, cb), axis=1)
        return (blocks_times(model, sym[0], sym[1], f(sym[2]), x)
                + scatter_pairs(N, ca, cb, coupled[:, None] * f(cL)).reshape(-1))

    x = _gmres(times, lambda r: sparsax.solve(*upper, r), b, GMRES_RTOL, GMRES_MAX)
    # GMRES has answered where its residual is within GMRES_RTOL, or within what forming
    # K x can resolve (a backward error of BACKWARD_ROUND_OFFS round-offs of |K| |x| + |b|):
    # near an answer, where R is small against the stiff springs' |K| |x|, the residual's
    # own rounding is above 1e-10 |b|. On seed example 3's slip tangent (10 slipping
    # slots) GMRES's residual stood at 7.0e-10 |b| from its 10th iteration, 0.48
    # round-offs of |K| |x| + |b|, and KLU's answer (then taken) left 8.2e-10 |b|, 0.56
    # round-offs, 5e-11 from GMRES's: that slip tangent cost a Cholesky factor, 40 GMRES
    # iterations and an LU, 171 ms against 33 ms a secant solve (BENCHMARKS.md,
    # "Thirty-seventh session").
    r = jnp.linalg.norm(b - times(x))
    floor = BACKWARD_ROUND_OFFS * jnp.finfo(b.dtype).eps * jnp.linalg.norm(
        times(jnp.abs(x), jnp.abs) + jnp.abs(b))
    ok = r <= jnp.maximum(10 * GMRES_RTOL * jnp.linalg.norm(b), floor)
    return jax.lax.cond(ok, lambda: x, fallback)


def _gmres(matvec, precond, b, rtol, m):
    """Right-preconditioned GMRES from x = 0: x = M y, (A M) y = b, until the residual's
    estimate is under rtol |b| or m iterations (no restart).

    Arnoldi with classical Gram-Schmidt twice (CGS2: as stable as modified
    Gram-Schmidt, and two matrix products instead of a loop), Givens rotations for the
    least-squares residual. Fixed shapes: the Krylov basis is an (m + 1, n) buffer.
    """
    beta = jnp.linalg.norm(b)
    V = jnp.zeros((m + 1, b.shape[0]), b.dtype).at[0].set(b / jnp.where(beta > 0, beta, 1.0))
    H = jnp.eye(m + 1, m, dtype=b.dtype)  # unused columns stay regular
    g = jnp.zeros(m + 1, b.dtype).at[0].set(beta)
    rot = jnp.zeros((m, 2), b.dtype)
    upto = jnp.arange(m + 1)

    def cond(c):
        j, _, _, g, _ = c
        return (j < m) & (jnp.abs(g[j]) > rtol * beta)

    def body(c):
        j, V, H, g, rot = c
        w = matvec(precond(V[j]))
        h = jnp.zeros(m + 1, b.dtype)
        for _ in range(2):  # CGS2
            hh = jnp.where(upto <= j, V @ w, 0.0)
            w = w - hh @ V
            h = h + hh
        hn = jnp.linalg.norm(w)
        V = V.at[j + 1].set(w / jnp.where(hn > 0, hn, 1.0))
        h = h.at[j + 1].set(hn)

        def rotate(i, h):
            cs, sn = rot[i]
            hi, hi1 = h[i], h[i + 1]
            return h.at[i].set(cs * hi + sn * hi1).at[i + 1].set(-sn * hi + cs * hi1)

        h = jax.lax.fori_loop(0, j, rotate, h)
        r = jnp.hypot(h[j], h[j + 1])
        r_safe = jnp.where(r > 0, r, 1.0)
        cs, sn = jnp.where(r > 0, h[j] / r_safe, 1.0), jnp.where(r > 0, h[j + 1] / r_safe, 0.0)
        h = h.at[j].set(r).at[j + 1].set(0.0)
        rot = rot.at[j].set(jnp.stack([cs, sn]))
        g = g.at[j + 1].set(-sn * g[j]).at[j].set(cs * g[j])
        return j + 1, V, H.at[:, j].set(h), g, rot

    j, V, H, g, _ = jax.lax.while_loop(cond, body, (0, V, H, g, rot))
    # R y = g by back substitution (R = H[:m, :m], upper triangular): written out rather
    # than LAPACK's triangular solve, the only LAPACK call of the sparse path's program,
    # whose set-up (SciPy's BLAS and LAPACK imported) cost 0.13 s of every run.
    R, rhs = H[:m, :m], jnp.where(upto[:m] < j, g[:m], 0.0)

    def back(i, y):
        k = m - 1 - i
        return y.at[k].set((rhs[k] - R[k] @ y) / R[k, k])

    y = jax.lax.fori_loop(0, m, back, jnp.zeros(m, b.dtype))
    return precond(y @ V[:m])


def coo_of_blocks(model: Model, rows, cols, blocks, upper=False, index=None):
    """COO triplets (int32 rows, int32 columns, float64 values) of the (D, D) blocks of
    :func:`stiffness_blocks`, as sparsax takes them (duplicates are summed there).

    ``upper``: of a symmetric matrix, only the off-diagonal blocks above the diagonal
    (of each pair, (first, second) or (second, first)) with the diagonal blocks, half
    the triplets: CHOLMOD reads the upper triangle alone. ``index``: their (Ai, Aj)
    formed before (:func:`sparse_pattern`), else formed here (:func:`coo_index`).
    """
    if upper:
        blocks = _upper(model, rows, cols, blocks)
    Ai, Aj = coo_index(model, rows, cols, upper) if index is None else index
    return Ai, Aj, blocks.reshape(-1).astype(jnp.float64)


def _upper(model: Model, rows, cols, x):
    """``x``, :func:`stiffness_blocks`'s blocks (or their rows or columns), in the upper
    triangle: of each pair's (first, second) and (second, first) the one above the
    diagonal, then the diagonal blocks."""
    M = (rows.shape[0] - model.n_blocks) // 2
    take = (rows[:M] > cols[:M]).reshape((M,) + (1,) * (x.ndim - 1))
    return jnp.concatenate([jnp.where(take, x[M:2 * M], x[:M]), x[2 * M:]])


def coo_index(model: Model, rows, cols, upper=False):
    """(Ai, Aj), int32: the COO rows and columns of :func:`coo_of_blocks`'s triplets."""
    if upper:
        rows, cols = _upper(model, rows, cols, rows), _upper(model, rows, cols, cols)
    D = model.ndof
    shape = rows.shape + (D, D)
    Ai = jnp.broadcast_to(D * rows[:, None, None] + jnp.arange(D)[:, None], shape)
    Aj = jnp.broadcast_to(D * cols[:, None, None] + jnp.arange(D)[None, :], shape)
    return Ai.reshape(-1).astype(jnp.int32), Aj.reshape(-1).astype(jnp.int32)


def sparse_lu(model: Model, rows, cols, blocks):
    """x = A^-1 b for (n,) or (n, p) b, A the sparse matrix of the (D, D) blocks, by KLU
    inside the program (sparsax); None where sparsax is not installed. The pattern's
    analysis and the numeric factor are cached by sparsax, so solves with the same
    values factorise once."""
    sparsax = _sparsax()
    if sparsax is None:
        return None
    Ai, Aj, Ax = coo_of_blocks(model, rows, cols, blocks)
    return lambda b: sparsax.lu_solve(Ai, Aj, Ax, b.astype(jnp.float64)).astype(b.dtype)


# Stopping rule of the iterative solve: the Newton loop's forcing term lies in
# [min, max] (relative 2-norm residual of CG); min is also the default.
CG_RTOL_MIN = {True: 1e-10, False: 1e-5}  # float64, float32
CG_RTOL_MAX = 1e-2


def compact_terms(model: Model, terms):
    """The rank-one terms with k != 0, packed into a fixed capacity (the product's cost).

    A slot list holds 2 V slots per candidate pair, of which a touching pair
    uses one or two (a corner, or the two ends of a face-to-face contact):
    the matrix-free product runs over 2 slots per candidate pair instead of
    2 V, V times fewer. Should more terms be nonzero than that
    (never seen: it needs more than two springs per pair on average over the
    padded pair list), the surplus ones are left out of the iteration matrix:
    it stays symmetric positive definite, Newton's residual still has every
    spring, and the outer iteration converges, linearly instead of
    quadratically.
    """
    a, b, B, k = terms
    m = k.shape[0]
    n_bolt = n_bolt_terms(model)
    cap = min(m, (m - n_bolt) * 2 // max(model.n_vertices * 2, 2) + n_bolt)
    if cap >= m:
        return terms
    (idx,) = jnp.nonzero(k != 0, size=cap, fill_value=0)
    keep = jnp.arange(cap) < jnp.sum(k != 0)
    return a[idx], b[idx], B[idx], jnp.where(keep, k[idx], 0.0)


def _pcg(matvec, precond, rhs, rtol, maxiter):
    """Preconditioned conjugate gradients from x = 0 until |r| <= rtol |rhs| (2-norms).

    Returns (x, iterations). ``rtol`` may be traced (an inexact-Newton forcing
    term). Fixed shapes, one ``lax.while_loop``; vmaps (members stop together).
    """
    dot = lambda u, v: jnp.sum(u * v)  # noqa: E731
    stop = (rtol * jnp.linalg.norm(rhs)) ** 2
    z = precond(rhs)
    init = (jnp.zeros_like(rhs), rhs, z, z, dot(rhs, z), jnp.array(0))

    def cond(c):
        return (dot(c[1], c[1]) > stop) & (c[5] < maxiter)

    def body(c):
        x, r, z, p, rz, it = c
        q = matvec(p)
        pq = dot(p, q)
        alpha = jnp.where(pq > 0, rz / jnp.where(pq > 0, pq, 1.0), 0.0)
        x = x + alpha * p
        r = r - alpha * q
        z = precond(r)
        rz_new = dot(r, z)
        beta = jnp.where(rz > 0, rz_new / jnp.where(rz > 0, rz, 1.0), 0.0)
        return x, r, z, z + beta * p, rz_new, it + 1

    x, _, _, _, _, it = jax.lax.while_loop(cond, body, init)
    return x, it


def solve_cg(model: Model, sub: Sub, terms, R, rtol=None):
    """(K_t + eps M)^-1 R by conjugate gradients, matrix-free, block-Jacobi preconditioned.

    The product K x is a gather/scatter over the springs with k != 0 (packed
    by :func:`compact_terms`): cost and memory linear in the number of
    contacts, and no host callback, so it runs on a GPU and batches under
    vmap. ``rtol`` is the relative residual at which CG stops (2-norm): the
    Newton loop passes an Eisenstat-Walker forcing term (it corrects what CG
    leaves; its residual test decides convergence), default 1e-10 (1e-5 in
    float32, which cannot resolve 1e-10).
    """
    N, nd = model.n_blocks, model.ndof
    a, b, B, k = compact_terms(model, terms) if sub.packed is None else terms
    pm = jnp.where(sub.free[:, None], model.pseudo_mass, 1.0)

    def matvec(x):
        y = scatter_pairs(N, a, b, B * (k * jnp.sum(B * gather_pairs(x, a, b), 1))[:, None])
        if sub.Kc is not None:
            y = y + jnp.einsum("nij,nj->ni", sub.Kc, x)
        return jnp.where(sub.free[:, None], y, 0.0) + pm * x

    def block(part):
        Bp = B[:, part]
        return k[:, None, None] * Bp[:, :, None] * Bp[:, None, :]

    D = (jax.ops.segment_sum(block(slice(0, nd)), a, N)
         + jax.ops.segment_sum(block(slice(nd, 2 * nd)), b, N))
    if sub.Kc is not None:
        D = D + sub.Kc
    D = jnp.where(sub.free[:, None, None], D, 0.0) + jax.vmap(jnp.diag)(pm)
    Dinv = jnp.linalg.inv(D)

    def precond(x):
        return jnp.einsum("nij,nj->ni", Dinv, x)

    if rtol is None:
        rtol = CG_RTOL_MIN[R.dtype == jnp.float64]
    x, _ = _pcg(matvec, precond, R, rtol, 4 * N * nd + 200)
    return x
