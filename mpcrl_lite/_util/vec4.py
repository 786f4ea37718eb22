"""Four float64 numbers as one value of numba code: an LLVM ``<4 x double>`` vector.

The compiled MPC kernel (:mod:`mpcrl_lite.mpc.backends.kernel_core`) solves four problems at
once by keeping each quantity of the four as one such value: ``vload(a, k)`` reads the four
numbers ``a.flat[k:k + 4]``, arithmetic on the values (``+ - * /``, unary ``-``, with each
other or with a float) is one vector instruction each, and ``vstore(a, k, v)`` writes them
back. numba's own loops over four problems stay scalar (it cannot prove the arrays distinct,
so its vectoriser gives up; ``benchmarks/README.md``); written with these values, the
compiler has nothing left to prove.

Every operation is IEEE arithmetic on each of the four numbers alone, exactly the scalar
operation (no fused multiply-add, no reordering): a computation written with these values
gives, in each lane, the bits of the same computation written with floats. The comparisons
copy numba's scalar ones: :func:`vmax` and :func:`vmin` are numba's ``max(acc, v)`` and
``min(acc, v)`` of two floats (``v`` where ``v > acc``, resp. ``v < acc``, else ``acc``: NaN
handling included), and ``where_gt(a, b, x, y)`` takes ``x`` where ``a > b`` (false for NaN).

The arrays must be C-contiguous float64; offsets are flat element offsets (nothing is
checked: meant for the kernel's own work arrays). A vector value cannot be returned to
Python: kernels store their results into arrays.
"""

from __future__ import annotations

import operator

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic, models, overload, register_model

__all__ = ["LANES", "f64x4", "vabs", "vload", "vmax", "vmin", "vsplat", "vstore", "where_gt",
           "where_lt"]

#: numbers per value
LANES = 4
_VEC = ir.VectorType(ir.DoubleType(), LANES)
_I32 = ir.IntType(32)


class F64x4(types.Type):
    """numba type of four float64 numbers held as one vector."""

    def __init__(self) -> None:
        super().__init__(name="f64x4")


f64x4 = F64x4()


@register_model(F64x4)
class _VectorModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type) -> None:
        super().__init__(dmm, fe_type, _VEC)


def _address(context, builder, array_type, array, offset):
    data = context.make_array(array_type)(context, builder, array).data
    return builder.bitcast(builder.gep(data, [offset]), _VEC.as_pointer())


@intrinsic
def vload(typingctx, a, k):
    """The four numbers ``a.flat[k:k + 4]``."""
    sig = f64x4(a, k)

    def codegen(context, builder, sig, args):
        return builder.load(_address(context, builder, sig.args[0], args[0], args[1]), align=8)
    return sig, codegen


@intrinsic
def vstore(typingctx, a, k, v):
    """``a.flat[k:k + 4] = v``."""
    sig = types.none(a, k, v)

    def codegen(context, builder, sig, args):
        builder.store(args[2], _address(context, builder, sig.args[0], args[0], args[1]),
                      align=8)
        return context.get_dummy_value()
    return sig, codegen


@intrinsic
def vsplat(typingctx, x):
    """Four copies of the float ``x``."""
    sig = f64x4(types.float64)

    def codegen(context, builder, sig, args):
        v = ir.Constant(_VEC, ir.Undefined)
        for i in range(LANES):
            v = builder.insert_element(v, args[0], ir.Constant(_I32, i))
        return v
    return sig, codegen


def _binary(instruction: str):
    @intrinsic
    def impl(typingctx, a, b):
        sig = f64x4(f64x4, f64x4)

        def codegen(context, builder, sig, args):
            return getattr(builder, instruction)(args[0], args[1])
        return sig, codegen
    return impl


_vadd, _vsub, _vmul, _vdiv = (_binary("fadd"), _binary("fsub"), _binary("fmul"),
                              _binary("fdiv"))


@intrinsic
def _vneg(typingctx, a):
    sig = f64x4(f64x4)

    def codegen(context, builder, sig, args):
        return builder.fneg(args[0])
    return sig, codegen


def _where(predicate: str):
    @intrinsic
    def impl(typingctx, a, b, x, y):
        sig = f64x4(f64x4, f64x4, f64x4, f64x4)

        def codegen(context, builder, sig, args):
            return builder.select(builder.fcmp_ordered(predicate, args[0], args[1]), args[2],
                                  args[3])
        return sig, codegen
    return impl


#: ``where_gt(a, b, x, y)``: ``x`` where ``a > b``, else ``y`` (false where either is NaN)
where_gt = _where(">")
#: ``where_lt(a, b, x, y)``: ``x`` where ``a < b``, else ``y``
where_lt = _where("<")


@intrinsic
def vabs(typingctx, a):
    """``|a|`` of each number (the sign bit cleared)."""
    sig = f64x4(f64x4)

    def codegen(context, builder, sig, args):
        fabs = cgutils.get_or_insert_function(builder.module, ir.FunctionType(_VEC, [_VEC]),
                                              "llvm.fabs.v4f64")
        return builder.call(fabs, [args[0]])
    return sig, codegen


def vmax(acc, v):
    """numba's ``max(acc, v)`` of two floats, number by number."""
    raise NotImplementedError("vmax runs in compiled code only")


def vmin(acc, v):
    """numba's ``min(acc, v)`` of two floats, number by number."""
    raise NotImplementedError("vmin runs in compiled code only")


@overload(vmax)
def _vmax(acc, v):
    return lambda acc, v: where_gt(v, acc, v, acc)


@overload(vmin)
def _vmin(acc, v):
    return lambda acc, v: where_lt(v, acc, v, acc)


def _number(t) -> bool:
    return isinstance(t, (types.Float, types.Integer))


def _arithmetic(op, impl) -> None:
    @overload(op)
    def _op(a, b):
        if isinstance(a, F64x4) and isinstance(b, F64x4):
            return lambda a, b: impl(a, b)
        if isinstance(a, F64x4) and _number(b):
            return lambda a, b: impl(a, vsplat(float(b)))
        if _number(a) and isinstance(b, F64x4):
            return lambda a, b: impl(vsplat(float(a)), b)
        return None


for _op, _impl in ((operator.add, _vadd), (operator.sub, _vsub), (operator.mul, _vmul),
                   (operator.truediv, _vdiv)):
    _arithmetic(_op, _impl)


@overload(operator.neg)
def _neg(a):
    if isinstance(a, F64x4):
        return lambda a: _vneg(a)
    return None
