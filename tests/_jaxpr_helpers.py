"""Reading the structure of a traced program (a `jax.make_jaxpr` result) in tests."""


def _subjaxprs(params):
    for value in params.values():
        for x in value if isinstance(value, tuple | list) else (value,):
            if hasattr(x, "eqns"):
                yield x
            elif hasattr(getattr(x, "jaxpr", None), "eqns"):
                yield x.jaxpr


def _contains(jaxpr, primitive: str) -> bool:
    return any(e.primitive.name == primitive or any(_contains(j, primitive) for j in _subjaxprs(e.params))
               for e in jaxpr.eqns)


def loop_under_cond(closed) -> bool:
    """Whether some `cond` of the program (at any depth) has a `scan` in one of its branches: a choice between two
    loops that runs one of them. Under `vmap` a `cond` on a mapped predicate becomes a `select_n` of both branches'
    results, its loops then outside any `cond`."""

    def search(jaxpr):
        for e in jaxpr.eqns:
            if e.primitive.name == "cond" and any(_contains(b.jaxpr, "scan") for b in e.params["branches"]):
                return True
            if any(search(j) for j in _subjaxprs(e.params)):
                return True
        return False

    return search(closed.jaxpr)


def runs_outside_cond(closed, primitive: str) -> bool:
    """Whether `primitive` appears in the program (at any depth) outside every `cond` branch: it then runs whatever
    the `cond`s choose."""

    def search(jaxpr):
        for e in jaxpr.eqns:
            if e.primitive.name == primitive:
                return True
            if e.primitive.name != "cond" and any(search(j) for j in _subjaxprs(e.params)):
                return True
        return False

    return search(closed.jaxpr)


def reduced_precision_products(closed) -> list[str]:
    """The matrix products and convolutions (`dot_general`, `conv_general_dilated`, at any depth) of the program
    whose precision is not HIGHEST for both operands: on a GPU JAX's default precision multiplies float32 matrices
    (and convolves float32 arrays) in TF32."""
    import jax

    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    found = []

    def search(jaxpr):
        for e in jaxpr.eqns:
            if (e.primitive.name in ("dot_general", "conv_general_dilated")
                    and e.params.get("precision") != highest):
                shapes = [v.aval.str_short() for v in e.invars]
                found.append(f"{e.primitive.name}{tuple(shapes)} precision={e.params.get('precision')}")
            for j in _subjaxprs(e.params):
                search(j)

    search(closed.jaxpr)
    return found
