"""Helpers shared by the self-sensing tests (circuits, observers, benches)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def jacfwd_vs_central_fd(fn, module, rel_step=1e-6, rtol=1e-5, atol_frac=1e-7):
    """Compare `jax.jacfwd` of `fn(module)` (an array) w.r.t. every inexact leaf with central differences.

    Returns the number of scalar parameters checked; asserts column by column, each column scaled by its own size.
    """
    params, static = eqx.partition(module, eqx.is_inexact_array)
    jac = jax.jit(jax.jacfwd(lambda p: fn(eqx.combine(p, static))))(params)
    leaves, treedef = jax.tree_util.tree_flatten(params)
    jac_leaves = treedef.flatten_up_to(jac)
    f_jit = jax.jit(lambda p: fn(eqx.combine(p, static)))
    f0 = f_jit(params)
    checked = 0
    for i, (leaf, jl) in enumerate(zip(leaves, jac_leaves)):
        leaf_np = np.asarray(leaf)
        for idx in np.ndindex(leaf_np.shape):
            x = leaf_np[idx]
            if x == 0:  # e.g. an exact operator's `smoothing`: no relative step exists; not a circuit parameter
                continue
            ad = np.asarray(jl)[(...,) + idx]
            # Step: relative to the parameter, enlarged (up to 1 %) when the parameter barely moves the output, so
            # that round-off in the output does not swamp the difference.
            f_scale = np.max(np.abs(np.asarray(f0)))
            ad_scale = max(np.max(np.abs(ad)), 1e-300)
            h = max(rel_step * abs(float(x)), min(1e-5 * f_scale / ad_scale, 1e-2 * abs(float(x))), 1e-300)
            plus, minus = leaf_np.copy(), leaf_np.copy()
            plus[idx] += h
            minus[idx] -= h
            lp = list(leaves)
            lp[i] = jnp.asarray(plus)
            lm = list(leaves)
            lm[i] = jnp.asarray(minus)
            fd = (np.asarray(f_jit(treedef.unflatten(lp))) - np.asarray(f_jit(treedef.unflatten(lm)))) / (2 * h)
            scale = max(np.max(np.abs(fd)), np.max(np.abs(ad)), 1e-300)
            np.testing.assert_allclose(ad / scale, fd / scale, rtol=0, atol=max(rtol, atol_frac),
                                       err_msg=f"leaf {i} index {idx}")
            checked += 1
    return checked
