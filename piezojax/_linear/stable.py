"""A transfer function that is stable by construction: a cascade of first- and second-order sections."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .._checks import PiezojaxValueError, as_float_array, check_scalar, check_value, check_vector, concrete_or_none
from .._dtypes import common_float_dtype, polymul
from .base import AbstractLinearSystem
from .transfer_function import TransferFunction, normalise_tf


class StableTransferFunction(AbstractLinearSystem):
    r"""A transfer function parametrised by its poles (and zeros), stable for every valid parameter value.

    $D(s) = \prod_i (s^2 + 2\zeta_i\omega_i s + \omega_i^2)\prod_j (s - p_j)$ (monic) and numerator $N(s)$, given
    either by zeros, $N(s) = \prod_i (s^2 + 2\zeta^z_i\omega^z_i s + (\omega^z_i)^2) \prod_j (s - z_j)$, or by
    coefficients `num` (highest power first), or $N = 1$ (all-pole):

    - `dc_normalised=True` (default): $G(s) = K\,\dfrac{N(s)}{N(0)}\,\dfrac{D(0)}{D(s)}$, so $G(0) = K$;
    - `dc_normalised=False`: $G(s) = K\,N(s)/D(s)$.

    Poles: $\omega_i > 0$, $\zeta_i > 0$ (any damping; $\zeta \ge 1$ is a pair of real poles), $p_j < 0$ — checked at
    construction (ValueError naming the argument) and with `eqx.error_if` whenever the realisation is built. Zeros are
    free ($\omega^z > 0$, $\zeta^z$ and $z_j$ of any sign: non-minimum-phase zeros are allowed). For fitting, wrap the
    pole parameters with the reparametrisations of `piezojax` (`Positive` for `omega`, `zeta`).

    **Realisation (why):** a cascade of sections, real poles first, then pole pairs, each section in a scaled form:
    $\dot x = p(x - u)$ for a real pole; $\dot x_1 = \omega x_2$, $\dot x_2 = \omega(u - x_1) - 2\zeta\omega x_2$
    for a pair (unit DC gain, entries of the size of the section's own frequency, well-conditioned eigenvectors even
    for $\zeta = 0.01$). Zeros are attached to sections (complex zero pair $i$ to pole pair $i$; real zero $j$ to
    real pole $j$, the remaining real zeros two per remaining pole pair), so each section is a local biquad and no
    ill-conditioned conversion between polynomial bases is needed. This keeps a creep pole at $10^{-4}$ rad/s and a
    resonance at $2\pi\cdot500$ rad/s both accurate over $10^6$ samples, where a companion form of the same
    polynomial mixes coefficients spanning 10 decades. A cascade, unlike a partial-fraction (parallel) form, needs
    no residues, which blow up for repeated or close poles — common while fitting. The slow (real) sections come
    first so that rounding in the coupling terms is filtered by the fast sections rather than integrated.

    With `num` instead of zeros, the output map solves $\sum_i C_i P_i(s) = N(s) - D_{ff} D(s)$ ($P_i/D$: transfer
    function from $u$ to state $i$), equilibrated; the result is exact but zeros far below the fast poles are then
    realised through the fast states and lose digits (measured: 4e-10 relative with a zero at 1.5e-4 rad/s next to
    a 500 Hz resonance, against 1e-14 with `zeros`). Prefer `zeros`.

    **Arguments:**

    - `gain`: $K$ (the DC gain when `dc_normalised`).
    - `omega`, `zeta`: natural frequencies (rad/s) and damping ratios of the pole pairs, shape `(n2,)`.
    - `poles`: real poles (rad/s), shape `(n1,)`, each < 0.
    - `zeros`: real zeros, shape `(m1,)`, at most `n1 + 2 (n2 - m2)`.
    - `zero_omega`, `zero_zeta`: complex zero pairs, shape `(m2,)`, `m2 <= n2`.
    - `num`: numerator coefficients instead of zeros, degree ≤ `2 n2 + n1`.
    - `dc_normalised`: see above (static).

    ```python
    G = pj.StableTransferFunction(2e-6, omega=[2 * jnp.pi * 500], zeta=[0.01], poles=[-1e-4], zeros=[-1.5e-4])
    G.dc_gain()      # 2e-6
    y = G.simulate(jnp.ones(10_000), 1e-4)
    ```
    """

    gain: Float[Array, ""]
    omega: Float[Array, " n2"]
    zeta: Float[Array, " n2"]
    poles: Float[Array, " n1"]
    zeros: Float[Array, " m1"]
    zero_omega: Float[Array, " m2"]
    zero_zeta: Float[Array, " m2"]
    num: Float[Array, " m"] | None
    dc_normalised: bool = eqx.field(static=True)

    def __init__(
        self,
        gain: ArrayLike = 1.0,
        omega: ArrayLike = (),
        zeta: ArrayLike = (),
        poles: ArrayLike = (),
        zeros: ArrayLike = (),
        zero_omega: ArrayLike = (),
        zero_zeta: ArrayLike = (),
        num: ArrayLike | None = None,
        dc_normalised: bool = True,
    ):
        args = {
            "gain": gain,
            "omega": omega,
            "zeta": zeta,
            "poles": poles,
            "zeros": zeros,
            "zero_omega": zero_omega,
            "zero_zeta": zero_zeta,
        }
        if num is not None:
            args["num"] = num
        raw = {k: as_float_array(v, k) for k, v in args.items()}
        dtype = common_float_dtype(*args.values())  # the arrays given decide; numbers and lists follow them
        gain = check_scalar(raw["gain"], "gain", dtype)
        vec = {k: check_vector(raw[k], k, dtype, allow_empty=True) for k in args if k not in ("gain", "num")}
        for a, b in (("omega", "zeta"), ("zero_omega", "zero_zeta")):
            if vec[a].shape != vec[b].shape:
                raise PiezojaxValueError(
                    f"`{a}` and `{b}` must have the same shape (one per pair), got {vec[a].shape} and {vec[b].shape}"
                )
        n2, n1 = vec["omega"].shape[0], vec["poles"].shape[0]
        m2, m1 = vec["zero_omega"].shape[0], vec["zeros"].shape[0]
        n = 2 * n2 + n1
        if num is not None:
            if m1 or m2:
                raise PiezojaxValueError(
                    "give the numerator either as `num` or as zeros (`zeros`, `zero_omega`), not both"
                )
            num = check_vector(jnp.atleast_1d(raw["num"]), "num", dtype)
            num_c = concrete_or_none(num)
            if num_c is not None and num.shape[0] > n + 1:
                nz = np.flatnonzero(num_c)  # leading zeros do not raise the degree
                lead = int(nz[0]) if nz.size else num.shape[0] - 1
                num = num[min(lead, num.shape[0] - n - 1) :]
            if num.shape[0] > n + 1:
                raise PiezojaxValueError(f"`num` has degree {num.shape[0] - 1} but the system has {n} poles: improper")
            if dc_normalised:
                message = "`num` must have a nonzero constant term when dc_normalised=True"
                num = check_value(num, lambda a: a[-1] != 0, message)
        if m2 > n2:
            raise PiezojaxValueError(
                f"`zero_omega` has {m2} complex zero pairs but there are only {n2} pole pairs (`omega`); "
                "give the numerator as `num` instead"
            )
        if m1 > n1 + 2 * (n2 - m2):
            raise PiezojaxValueError(
                f"`zeros` has {m1} real zeros but only {n1 + 2 * (n2 - m2)} can be attached to the remaining sections "
                f"(one per real pole, two per pole pair without complex zeros); the system would be improper"
            )
        self.gain = gain
        self.omega = _check_sign(vec["omega"], "omega", positive=True)
        self.zeta = _check_sign(vec["zeta"], "zeta", positive=True)
        self.poles = _check_sign(vec["poles"], "poles", positive=False)
        self.zero_omega = _check_sign(vec["zero_omega"], "zero_omega", positive=True)
        self.zero_zeta = vec["zero_zeta"]
        zeros = vec["zeros"]
        if dc_normalised:
            zeros = check_value(zeros, lambda a: jnp.all(a != 0), "`zeros` must be nonzero when dc_normalised=True")
        self.zeros = zeros
        self.num = num
        self.dc_normalised = bool(dc_normalised)

    @property
    def order(self) -> int:
        return 2 * self.omega.shape[0] + self.poles.shape[0]

    # -- sections --------------------------------------------------------------------------------------------

    def _sections(self, omega, zeta, poles):
        """Cascade order: list of (den (highest first, monic), g = den(0), zero polynomial (monic) or None)."""
        dtype = self.gain.dtype
        one = jnp.ones((), dtype)
        n1, n2 = poles.shape[0], omega.shape[0]
        m1, m2 = self.zeros.shape[0], self.zero_omega.shape[0]
        zero_polys = {}
        # real zeros: first one per real pole, then two per pole pair without complex zeros
        slots = [("real", j) for j in range(n1)] + [("pair", i) for i in range(m2, n2) for _ in range(2)]
        for k in range(m1):
            key = slots[k]
            factor = jnp.stack([one, -self.zeros[k]])
            zero_polys[key] = factor if key not in zero_polys else polymul(zero_polys[key], factor)
        for i in range(m2):
            wz, zz = self.zero_omega[i], self.zero_zeta[i]
            zero_polys[("pair", i)] = jnp.stack([one, 2 * zz * wz, wz * wz])
        out = []
        for j in range(n1):
            out.append(("real", poles[j : j + 1], jnp.stack([one, -poles[j]]), -poles[j], zero_polys.get(("real", j))))
        for i in range(n2):
            w, z = omega[i], zeta[i]
            out.append(("pair", (w, z), jnp.stack([one, 2 * z * w, w * w]), w * w, zero_polys.get(("pair", i))))
        return out

    def _checked(self) -> "StableTransferFunction":
        """`self` with one value check of every parameter attached (stable poles, finite zeros, gain and `num`): one
        `check_value`, i.e. one `eqx.branched_error_if` to compile when traced. Also catches values replaced after
        `__init__` (`eqx.tree_at`)."""
        names = ("omega", "zeta", "poles", "gain", "zeros", "zero_omega", "zero_zeta")
        names += ("num",) if self.num is not None else ()

        def ok(p):
            omega, zeta, poles, *rest = p
            finite = [jnp.all(jnp.isfinite(x)) for x in p]
            signs = [jnp.all(omega > 0), jnp.all(zeta > 0), jnp.all(poles < 0), jnp.all(p[5] > 0)]
            return jnp.stack(
                [finite[0] & signs[0], finite[1] & signs[1], finite[2] & signs[2]]
                + finite[3:5]
                + [finite[5] & signs[3]]
                + finite[6:]
            )

        messages = [
            "`omega` must be finite and positive (stable)",
            "`zeta` must be finite and positive (stable)",
            "`poles` must be finite and negative (stable)",
            "`gain` contains NaN or infinite values",
            "`zeros` contains NaN or infinite values",
            "`zero_omega` must be finite and positive",
            "`zero_zeta` contains NaN or infinite values",
            "`num` contains NaN or infinite values",
        ][: len(names)]
        params = check_value(tuple(getattr(self, n) for n in names), ok, messages)
        return eqx.tree_at(lambda m: tuple(getattr(m, n) for n in names), self, params)

    # -- polynomials -----------------------------------------------------------------------------------------

    def denominator(self) -> Float[Array, " n+1"]:
        """The monic denominator $D(s)$, highest power first."""
        den = jnp.ones((1,), self.gain.dtype)
        for sec in self._sections(self.omega, self.zeta, self.poles):
            den = polymul(den, sec[2])
        return den

    def _zero_numerator(self) -> Array:
        num = jnp.ones((1,), self.gain.dtype)
        for sec in self._sections(self.omega, self.zeta, self.poles):
            if sec[4] is not None:
                num = polymul(num, sec[4])
        return num

    def numerator(self) -> Float[Array, " n+1"]:
        r"""The numerator $K(s)$ of $G(s) = K(s)/D(s)$ with monic $D$, highest power first, length n + 1."""
        dtype = self.gain.dtype
        n = self.order
        num = self._zero_numerator() if self.num is None else self.num
        k = self.gain * self.denominator()[-1] / num[-1] if self.dc_normalised else self.gain
        num = k * num
        return jnp.concatenate([jnp.zeros((n + 1 - num.shape[0],), dtype), num])

    def transfer_function(self) -> tuple[Float[Array, " n+1"], Float[Array, " n+1"]]:
        """`(num, den)` polynomial coefficients, highest power first, `den` monic."""
        return self.numerator(), self.denominator()

    def to_tf(self) -> TransferFunction:
        """The same system as a `TransferFunction` (polynomial coefficients)."""
        return TransferFunction(*self.transfer_function())

    # -- realisation -----------------------------------------------------------------------------------------

    def state_space(self):
        return self._checked()._state_space()

    def _state_space(self):
        dtype = self.gain.dtype
        omega, zeta, poles = self.omega, self.zeta, self.poles
        n = self.order
        sections = self._sections(omega, zeta, poles)
        zero = jnp.zeros((), dtype)
        # Assembled from scalar entries and stacked once (one op instead of a scatter per entry: compile time).
        A = [[zero] * n for _ in range(n)]
        B = [zero] * n
        C_out = [zero] * n  # output map of the cascade so far: y_k = C_out x + D_out u
        D_out = jnp.ones((), dtype)
        total = jnp.ones((), dtype)  # product of the sections' DC gains (for the overall normalisation)
        k = 0
        for kind, params, _, _, zpoly in sections:
            if kind == "real":
                (p,) = params
                Ak, Bk = [[p]], [-p]
                if zpoly is None:  # -p/(s - p): output x
                    Ck, Dk, sec_dc = [jnp.ones((), dtype)], zero, jnp.ones((), dtype)
                else:  # (s - z)/(s - p) = 1 + ((z - p)/p) x
                    z = -zpoly[1]
                    Ck, Dk, sec_dc = [(z - p) / p], jnp.ones((), dtype), z / p
            else:
                w, zt = params
                Ak, Bk = [[zero, w], [-w, -2 * zt * w]], [zero, w]
                if zpoly is None:  # w^2 / d(s): output x1
                    Ck, Dk, sec_dc = [jnp.ones((), dtype), zero], zero, jnp.ones((), dtype)
                else:  # (b0 s^2 + b1 s + b2)/d(s) with x1 = w^2/d u, s x1 = w x2, s^2 x1 = w^2 (u - x1 - 2 zeta x2)
                    b = [zero] * (3 - zpoly.shape[0]) + [zpoly[i] for i in range(zpoly.shape[0])]
                    Ck = [b[2] / (w * w) - b[0], b[1] / w - 2 * zt * b[0]]
                    Dk, sec_dc = b[0], b[2] / (w * w)
            width = len(Bk)
            for r in range(width):
                for c in range(width):
                    A[k + r][k + c] = Ak[r][c]
                # the section's input is the previous output C_out x + D_out u
                for c in range(k):
                    A[k + r][c] = Bk[r] * C_out[c]
                B[k + r] = Bk[r] * D_out
            C_out = [C_out[c] * Dk for c in range(k)] + Ck + C_out[k + width :]
            D_out = D_out * Dk
            total = total * sec_dc
            k += width
        A = jnp.stack([jnp.stack(row) for row in A]) if n else jnp.zeros((0, 0), dtype)
        B = jnp.stack(B) if n else jnp.zeros((0,), dtype)
        C_out = jnp.stack(C_out) if n else jnp.zeros((0,), dtype)
        if self.num is not None and n > 0:
            return self._num_realisation(A, B, omega, zeta, poles, sections)
        if self.dc_normalised:
            scale = self.gain / total
        else:
            # sections are N_k / d_k for zero sections and g_k / d_k for all-pole ones
            scale = self.gain
            for _, _, _, g, zpoly in sections:
                if zpoly is None:
                    scale = scale / g
        if self.num is not None:  # n == 0: a static gain
            scale = scale * (self.num[-1] if not self.dc_normalised else 1.0)
        return A, B, scale * C_out, scale * D_out

    def _num_realisation(self, A, B, omega, zeta, poles, sections):
        """All-pole cascade with the output map solved for the coefficient numerator `num` (see class doc)."""
        dtype = self.gain.dtype
        n = self.order
        K = self.numerator()
        den = self.denominator()
        Dff = K[0]
        R = (K - Dff * den)[1:]
        # Column i: P_i(s) with X_i(s) = P_i(s) U(s) / D(s), for the all-pole cascade built above.
        cols = []
        dc = jnp.ones((), dtype)
        for s_idx, (kind, params, _, g, _) in enumerate(sections):
            dc = dc * g
            rest = jnp.ones((1,), dtype)
            for later in sections[s_idx + 1 :]:
                rest = polymul(rest, later[2])
            p1 = dc * rest
            cols.append(p1)
            if kind == "pair":  # x2 = s x1 / omega
                cols.append(jnp.concatenate([p1, jnp.zeros((1,), dtype)]) / params[0])
        M = jnp.stack([jnp.concatenate([jnp.zeros((n - c.shape[0],), dtype), c]) for c in cols], axis=1)
        return A, B, _equilibrated_solve(M, R), Dff

    # -- construction from polynomials -----------------------------------------------------------------------

    @classmethod
    def from_tf(cls, num: ArrayLike, den: ArrayLike, dc_normalised: bool = False) -> "StableTransferFunction":
        r"""Factor a stable denominator into sections (concrete values only; uses `numpy.roots`).

        Complex root pairs $r, \bar r$ become $\omega = |r|$, $\zeta = -\mathrm{Re}\,r/|r|$; real roots stay real
        poles. The numerator is kept as coefficients (`num`). Raises a `ValueError` naming `den` if any root has a
        non-negative real part.

        **Arguments:**

        - `num`, `den`: coefficients, highest power first (as `TransferFunction`).
        - `dc_normalised`: the returned parametrisation (the transfer function is the same either way).

        **Returns:** a `StableTransferFunction` equal to `num/den`.

        ```python
        G = pj.StableTransferFunction.from_tf([1.0], [1.0, 0.2, 100.0])  # omega = 10, zeta = 0.01
        ```
        """
        num_n, den_n = normalise_tf(num, den)
        num_c, den_c = concrete_or_none(num_n), concrete_or_none(den_n)
        if num_c is None or den_c is None:
            raise PiezojaxValueError("`StableTransferFunction.from_tf` needs concrete `num` and `den` (not traced)")
        roots = np.roots(den_c)
        if np.any(roots.real >= 0):
            raise PiezojaxValueError(
                f"`den` has roots with non-negative real part {roots[roots.real >= 0].tolist()}: not stable"
            )
        scale = max(1.0, float(np.max(np.abs(roots)))) if roots.size else 1.0
        is_real = np.abs(roots.imag) <= 1e-12 * scale
        real = np.sort(roots[is_real].real)[::-1]
        upper = roots[~is_real & (roots.imag > 0)]
        omega = np.abs(upper)
        zeta = -upper.real / omega
        dtype = den_n.dtype
        nz = np.flatnonzero(num_c)
        num_trim = num_n[int(nz[0]) if nz.size else num_c.shape[0] - 1 :]
        as_dtype = lambda x: jnp.asarray(x, dtype)  # noqa: E731
        if dc_normalised:
            gain = float(num_c[-1]) / float(np.prod(omega**2) * np.prod(-real))
            return cls(as_dtype(gain), as_dtype(omega), as_dtype(zeta), as_dtype(real), num=num_trim)
        return cls(as_dtype(1.0), as_dtype(omega), as_dtype(zeta), as_dtype(real), num=num_trim, dc_normalised=False)


def _check_sign(x: Array, name: str, positive: bool) -> Array:
    """Elementwise > 0 (or < 0) and finite (`check_value`)."""
    what = "positive" if positive else "negative"
    ok = (lambda a: jnp.all(jnp.isfinite(a) & (a > 0))) if positive else (lambda a: jnp.all(jnp.isfinite(a) & (a < 0)))
    return check_value(x, ok, f"`{name}` must be finite and {what} (stable)")


def _pow2_scale(m: Array) -> Array:
    """Power-of-two reciprocals of `m` (exact scaling), 1 where `m` is 0; no gradient (the solution is invariant)."""
    m = jax.lax.stop_gradient(m)
    safe = jnp.where(m > 0, m, jnp.ones_like(m))
    return jnp.exp2(-jnp.round(jnp.log2(safe)))


def _equilibrated_solve(M: Array, r: Array) -> Array:
    """Solve `M c = r` after column then row equilibration.

    The columns of M span many decades when the poles do; plain partial pivoting lost 8 digits of C in a measured
    case (creep pole 1e-4 rad/s with a 500 Hz resonance); equilibrated, C was exact to rounding.
    """
    cs = _pow2_scale(jnp.max(jnp.abs(M), axis=0))
    M1 = M * cs
    rs = _pow2_scale(jnp.max(jnp.abs(M1), axis=1))
    return jnp.linalg.solve(M1 * rs[:, None], r * rs) * cs
