"""Fixed-width SIMD vectors inside numba kernels: a `Vec` of LANES floats (or int32) and its `Mask`.

Why by hand: numba has no vector type, and LLVM's loop vectorizer compiled the compositing's
16-pixel lane loops unevenly: the blend loop ran in 128-bit and scalar code behind runtime alias
checks between its arrays, and a fused alpha-and-blend loop was not vectorized at all. Here each
value is one LLVM vector (`<16 x float>`), which LLVM lowers to whatever registers the CPU has
(one AVX-512 register, two AVX2 ones, four NEON ones), so the kernels are vectorized by
construction. Nothing in NumPy, numba or llvmlite offers this.

Every operation is plain IEEE arithmetic without fast-math flags, so LLVM may not reorder or fuse
it: a function computes the same bits wherever it is inlined (the compositing's forward and
backward rely on this for alpha). `fma` is LLVM's fused multiply-add, one rounding, on every CPU.

    v = load(array, row, col)          # array[row, col:col + LANES] of a C-contiguous 2D array
    store(array, row, col, v)
    splat(x)                           # LANES copies of a scalar
    a + b, a - b, a * b, a / b, -a     # with a Vec or a scalar of its type on either side
    a < b, a <= b, a > b, a >= b, a == b, a != b   # -> Mask (ordered; != is unordered, as Python's)
    m & n, m | n, ~m                   # masks
    select(m, a, b), fma(a, b, c), min(a, b), max(a, b) (also vmin, vmax)
    any_lane(m), count(m), lane(a, j)
    lane_sums((a, b, ...))             # lane k: the sum of the lanes of the k-th Vec
    load_at(array, at, col), store_at(array, at, col, v)  # at = (row,): a whole row; at =
                                       # (row_lo, off_lo, row_hi, off_hi): two half rows as one Vec
    load_first(array, row, col, n), store_first(array, row, col, v, n)   # the first n lanes only
    half_iota(ft), upper_lanes()
"""

from __future__ import annotations

import operator

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.core.errors import TypingError
from numba.extending import intrinsic, models, overload, register_model

LANES = 16


class Vec(types.Type):
    """LANES values of one numba scalar type (float32, float64 or int32) in one LLVM vector."""

    def __init__(self, dtype):
        self.dtype = dtype
        super().__init__(name=f"Vec{LANES}[{dtype}]")


class Mask(types.Type):
    """LANES booleans, as LLVM's <LANES x i1>."""

    def __init__(self):
        super().__init__(name=f"Mask{LANES}")


mask_type = Mask()


@register_model(Vec)
class _VecModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, ir.VectorType(dmm.lookup(fe_type.dtype).get_value_type(), LANES))


@register_model(Mask)
class _MaskModel(models.PrimitiveModel):
    def __init__(self, dmm, fe_type):
        super().__init__(dmm, fe_type, ir.VectorType(ir.IntType(1), LANES))


def _vector_type(context, dtype):
    return ir.VectorType(context.get_value_type(dtype), LANES)


def _splat(builder, value, vector_type):
    """LANES copies of an LLVM scalar (insert into lane 0, then shuffle lane 0 everywhere)."""
    first = builder.insert_element(ir.Constant(vector_type, ir.Undefined), value, ir.Constant(ir.IntType(32), 0))
    zeros = ir.Constant(ir.VectorType(ir.IntType(32), LANES), [0] * LANES)
    return builder.shuffle_vector(first, ir.Constant(vector_type, ir.Undefined), zeros)


def _pointer(context, builder, array_type, array, row, col):
    data = context.make_array(array_type)(context, builder, array)
    return cgutils.get_item_pointer(context, builder, array_type, data, [row, col], wraparound=False)


def _check_rows(array):
    if not (isinstance(array, types.Array) and array.ndim == 2 and array.layout == "C"):
        raise TypingError(f"simd loads and stores take C-contiguous 2D arrays, not {array}")


def _load_lanes(context, builder, dtype, pointer, lanes):
    """`lanes` consecutive elements of dtype at pointer as one LLVM vector (aligned as one element)."""
    vector_type = ir.VectorType(context.get_value_type(dtype), lanes)
    align = context.get_abi_sizeof(context.get_value_type(dtype))
    return builder.load(builder.bitcast(pointer, vector_type.as_pointer()), align=align)


def _store_lanes(context, builder, dtype, pointer, value):
    """The inverse of `_load_lanes`: the LLVM vector value to consecutive elements at pointer."""
    align = context.get_abi_sizeof(context.get_value_type(dtype))
    builder.store(value, builder.bitcast(pointer, value.type.as_pointer()), align=align)


@intrinsic
def load(typingctx, array, row, col):
    """array[row, col:col + LANES] as one Vec (no bounds check)."""
    _check_rows(array)
    vec = Vec(array.dtype)

    def codegen(context, builder, signature, args):
        pointer = _pointer(context, builder, array, args[0], args[1], args[2])
        return _load_lanes(context, builder, array.dtype, pointer, LANES)

    return vec(array, row, col), codegen


@intrinsic
def store(typingctx, array, row, col, value):
    """array[row, col:col + LANES] = value (no bounds check)."""
    _check_rows(array)
    if not (isinstance(value, Vec) and value.dtype == array.dtype):
        raise TypingError(f"cannot store {value} into {array}")

    def codegen(context, builder, signature, args):
        pointer = _pointer(context, builder, array, args[0], args[1], args[2])
        _store_lanes(context, builder, array.dtype, pointer, args[3])
        return context.get_dummy_value()

    return types.void(array, row, col, value), codegen


@intrinsic
def splat(typingctx, value):
    """LANES copies of a scalar (float32, float64 or int32)."""
    if not isinstance(value, (types.Float, types.Integer)):
        raise TypingError(f"cannot splat {value}")
    dtype = value if isinstance(value, types.Float) else types.int32

    def codegen(context, builder, signature, args):
        scalar = context.cast(builder, args[0], value, dtype)
        return _splat(builder, scalar, _vector_type(context, dtype))

    return Vec(dtype)(value), codegen


def _binary(float_op, int_op):
    @intrinsic
    def op(typingctx, a, b):
        if not (isinstance(a, Vec) and a == b):
            raise TypingError(f"vector operands differ: {a}, {b}")
        is_float = isinstance(a.dtype, types.Float)
        method = float_op if is_float else int_op

        def codegen(context, builder, signature, args):
            return getattr(builder, method)(args[0], args[1])

        return a(a, b), codegen

    return op


_add = _binary("fadd", "add")
_sub = _binary("fsub", "sub")
_mul = _binary("fmul", "mul")
_div = _binary("fdiv", "sdiv")


def _compare(symbol):
    @intrinsic
    def op(typingctx, a, b):
        if not (isinstance(a, Vec) and a == b):
            raise TypingError(f"vector operands differ: {a}, {b}")

        def codegen(context, builder, signature, args):
            if isinstance(a.dtype, types.Float):
                if symbol == "!=":
                    return builder.fcmp_unordered(symbol, args[0], args[1])
                return builder.fcmp_ordered(symbol, args[0], args[1])
            return builder.icmp_signed(symbol, args[0], args[1])

        return mask_type(a, b), codegen

    return op


def _register_binary(python_op, vector_op):
    @overload(python_op)
    def _overload(a, b):
        if isinstance(a, Vec) and isinstance(b, Vec):
            return lambda a, b: vector_op(a, b)
        if isinstance(a, Vec) and isinstance(b, (types.Float, types.Integer)):
            return lambda a, b: vector_op(a, _splat_like(b, a))
        if isinstance(b, Vec) and isinstance(a, (types.Float, types.Integer)):
            return lambda a, b: vector_op(_splat_like(a, b), b)
        return None


@intrinsic
def _splat_like(typingctx, value, like):
    """LANES copies of a scalar, cast to the element type of the Vec `like`."""
    if not (isinstance(like, Vec) and isinstance(value, (types.Float, types.Integer))):
        raise TypingError(f"cannot splat {value} like {like}")

    def codegen(context, builder, signature, args):
        scalar = context.cast(builder, args[0], value, like.dtype)
        return _splat(builder, scalar, _vector_type(context, like.dtype))

    return like(value, like), codegen


for _python_op, _vector_op in (
    (operator.add, _add),
    (operator.sub, _sub),
    (operator.mul, _mul),
    (operator.truediv, _div),
    (operator.lt, _compare("<")),
    (operator.le, _compare("<=")),
    (operator.gt, _compare(">")),
    (operator.ge, _compare(">=")),
    (operator.eq, _compare("==")),
    (operator.ne, _compare("!=")),
):
    _register_binary(_python_op, _vector_op)


@intrinsic
def _neg(typingctx, a):
    def codegen(context, builder, signature, args):
        if isinstance(a.dtype, types.Float):
            return builder.fneg(args[0])
        return builder.neg(args[0])

    return a(a), codegen


@overload(operator.neg)
def _overload_neg(a):
    if isinstance(a, Vec):
        return lambda a: _neg(a)
    return None


def _mask_binary(method):
    @intrinsic
    def op(typingctx, a, b):
        def codegen(context, builder, signature, args):
            return getattr(builder, method)(args[0], args[1])

        return mask_type(a, b), codegen

    return op


_and, _or = _mask_binary("and_"), _mask_binary("or_")


@intrinsic
def _not(typingctx, a):
    def codegen(context, builder, signature, args):
        return builder.not_(args[0])

    return mask_type(a), codegen


@overload(operator.and_)
def _overload_and(a, b):
    if isinstance(a, Mask) and isinstance(b, Mask):
        return lambda a, b: _and(a, b)
    return None


@overload(operator.or_)
def _overload_or(a, b):
    if isinstance(a, Mask) and isinstance(b, Mask):
        return lambda a, b: _or(a, b)
    return None


@overload(operator.invert)
def _overload_invert(a):
    if isinstance(a, Mask):
        return lambda a: _not(a)
    return None


@intrinsic
def select(typingctx, condition, a, b):
    """a where the mask is set, else b (per lane)."""
    if not (isinstance(condition, Mask) and isinstance(a, Vec) and a == b):
        raise TypingError(f"select({condition}, {a}, {b})")

    def codegen(context, builder, signature, args):
        return builder.select(args[0], args[1], args[2])

    return a(condition, a, b), codegen


@intrinsic
def fma(typingctx, a, b, c):
    """a * b + c with one rounding (LLVM's llvm.fma), per lane; scalars among the operands are
    splatted to the Vec's type, and three scalars of one float type give a scalar."""
    vectors = [x for x in (a, b, c) if isinstance(x, Vec)]
    if vectors:
        result = vectors[0]
        if not (isinstance(result.dtype, types.Float) and all(x == result for x in vectors)):
            raise TypingError(f"fma({a}, {b}, {c})")
        if not all(isinstance(x, (Vec, types.Float, types.Integer)) for x in (a, b, c)):
            raise TypingError(f"fma({a}, {b}, {c})")
    elif isinstance(a, types.Float) and a == b == c:
        result = a
    else:
        raise TypingError(f"fma({a}, {b}, {c})")

    def codegen(context, builder, signature, args):
        dtype = result.dtype if isinstance(result, Vec) else result
        llvm_type = _vector_type(context, dtype) if isinstance(result, Vec) else context.get_value_type(dtype)
        operands = []
        for value, value_type in zip(args, signature.args):
            if isinstance(result, Vec) and not isinstance(value_type, Vec):
                value = _splat(builder, context.cast(builder, value, value_type, dtype), llvm_type)
            operands.append(value)
        suffix = (
            ("f32" if dtype == types.float32 else "f64")
            if not isinstance(result, Vec)
            else (f"v{LANES}f32" if dtype == types.float32 else f"v{LANES}f64")
        )
        function_type = ir.FunctionType(llvm_type, [llvm_type] * 3)
        fn = cgutils.get_or_insert_function(builder.module, function_type, f"llvm.fma.{suffix}")
        return builder.call(fn, operands)

    return result(a, b, c), codegen


def _pick(name, symbol):
    @intrinsic
    def op(typingctx, a, b):
        if not (isinstance(a, Vec) and a == b):
            raise TypingError(f"{name}({a}, {b})")

        def codegen(context, builder, signature, args):
            return builder.select(builder.fcmp_ordered(symbol, args[0], args[1]), args[0], args[1])

        return a(a, b), codegen

    op.__doc__ = f"Per lane a if a {symbol} b else b."
    return op


vmin = _pick("vmin", "<")  # Python's min for numbers that are not NaN
vmax = _pick("vmax", ">")


_register_binary(min, vmin)
_register_binary(max, vmax)


def _mask_bits(builder, value):
    return builder.bitcast(value, ir.IntType(LANES))


@intrinsic
def any_lane(typingctx, m):
    """Whether any lane of the mask is set."""

    def codegen(context, builder, signature, args):
        bits = _mask_bits(builder, args[0])
        return builder.icmp_unsigned("!=", bits, ir.Constant(bits.type, 0))

    return types.boolean(m), codegen


@intrinsic
def count(typingctx, m):
    """How many lanes of the mask are set (an int64)."""

    def codegen(context, builder, signature, args):
        bits = _mask_bits(builder, args[0])
        fn = builder.module.declare_intrinsic("llvm.ctpop", [bits.type])
        return builder.zext(builder.call(fn, [bits]), ir.IntType(64))

    return types.int64(m), codegen


def _check_at(at):
    if not (isinstance(at, types.UniTuple) and len(at) in (1, 4) and isinstance(at.dtype, types.Integer)):
        raise TypingError(f"a place of LANES pixels is (row,) or (row_lo, offset_lo, row_hi, offset_hi), not {at}")


def _at_pointers(context, builder, array_type, array, at_type, at, col):
    """The pointers to the one whole row, or to the two half rows, that `at` names at column col."""
    parts = [builder.extract_value(at, j) for j in range(len(at_type))]
    if len(parts) == 1:
        return [_pointer(context, builder, array_type, array, parts[0], col)]
    return [
        _pointer(context, builder, array_type, array, parts[0], builder.add(col, parts[1])),
        _pointer(context, builder, array_type, array, parts[2], builder.add(col, parts[3])),
    ]


@intrinsic
def load_at(typingctx, array, at, col):
    """The LANES pixels at a place: at = (row,) reads array[row, col:col + LANES] in one load (as
    `load`); at = (row_lo, offset_lo, row_hi, offset_hi) reads array[row_lo, col + offset_lo:...]
    into the lower LANES / 2 lanes and array[row_hi, col + offset_hi:...] into the upper ones, two
    half-width loads. Which one is decided by the type of at, when compiling (no bounds check)."""
    _check_rows(array)
    _check_at(at)
    vec = Vec(array.dtype)

    def codegen(context, builder, signature, args):
        col = context.cast(builder, args[2], signature.args[2], signature.args[1].dtype)
        pointers = _at_pointers(context, builder, array, args[0], signature.args[1], args[1], col)
        if len(pointers) == 1:
            return _load_lanes(context, builder, array.dtype, pointers[0], LANES)
        halves = [_load_lanes(context, builder, array.dtype, p, LANES // 2) for p in pointers]
        both = ir.Constant(ir.VectorType(ir.IntType(32), LANES), list(range(LANES)))
        return builder.shuffle_vector(halves[0], halves[1], both)

    return vec(array, at, col), codegen


@intrinsic
def store_at(typingctx, array, at, col, value):
    """The inverse of `load_at`: value to the LANES pixels at a place (one store, or two halves)."""
    _check_rows(array)
    _check_at(at)
    if not (isinstance(value, Vec) and value.dtype == array.dtype):
        raise TypingError(f"cannot store {value} into {array}")

    def codegen(context, builder, signature, args):
        col = context.cast(builder, args[2], signature.args[2], signature.args[1].dtype)
        pointers = _at_pointers(context, builder, array, args[0], signature.args[1], args[1], col)
        if len(pointers) == 1:
            _store_lanes(context, builder, array.dtype, pointers[0], args[3])
            return context.get_dummy_value()
        i32 = ir.IntType(32)
        for k, pointer in enumerate(pointers):
            lanes = ir.Constant(ir.VectorType(i32, LANES // 2), list(range(k * LANES // 2, (k + 1) * LANES // 2)))
            part = builder.shuffle_vector(args[3], ir.Constant(args[3].type, ir.Undefined), lanes)
            _store_lanes(context, builder, array.dtype, pointer, part)
        return context.get_dummy_value()

    return types.void(array, at, col, value), codegen


@intrinsic
def half_iota(typingctx, dtype):
    """0, 1, ..., LANES / 2 - 1 twice, as a Vec of the float type given as its class."""
    ft = dtype.dtype if isinstance(dtype, types.NumberClass) else dtype.instance_type

    def codegen(context, builder, signature, args):
        vector_type = _vector_type(context, ft)
        values = [float(j % (LANES // 2)) for j in range(LANES)]
        return ir.Constant(vector_type, [ir.Constant(vector_type.element, v) for v in values])

    return Vec(ft)(dtype), codegen


@intrinsic
def upper_lanes(typingctx):
    """The mask of the upper half of the lanes (LANES / 2 .. LANES - 1)."""

    def codegen(context, builder, signature, args):
        bits = [ir.Constant(ir.IntType(1), int(j >= LANES // 2)) for j in range(LANES)]
        return ir.Constant(ir.VectorType(ir.IntType(1), LANES), bits)

    return mask_type(), codegen


@intrinsic
def lane_sums(typingctx, vectors):
    """A Vec whose lane k is the sum of the lanes of vectors[k] (a tuple of at most LANES Vecs;
    lanes past the tuple are 0), by a butterfly of shuffles and adds: each step adds the two
    halves of every group of lanes while packing two vectors into one, 15 adds for 16 vectors
    where summing each alone would take 64. A fixed order on every CPU, so sums are reproducible."""
    if not (isinstance(vectors, types.UniTuple) and isinstance(vectors.dtype, Vec) and vectors.count <= LANES):
        raise TypingError(f"lane_sums takes a tuple of at most {LANES} Vecs, not {vectors}")
    vec = vectors.dtype

    def codegen(context, builder, signature, args):
        vector_type = _vector_type(context, vec.dtype)
        i32 = ir.IntType(32)
        values = [builder.extract_value(args[0], k) for k in range(vectors.count)]
        values += [ir.Constant(vector_type, [ir.Constant(vector_type.element, 0.0)] * LANES)] * (LANES - vectors.count)
        group = LANES  # lanes per partial sum
        while len(values) > 1:
            # Pairs (a, b) -> c holding a's groups of lanes, then b's, each half as wide: the sum of
            # the lower and the upper half of every group (b's lanes are LANES.. in the shuffle).
            half, n = group // 2, LANES // group
            lower = [g * group + j for g in range(n) for j in range(half)]
            upper = [g * group + half + j for g in range(n) for j in range(half)]
            pick_lower = ir.Constant(ir.VectorType(i32, LANES), lower + [LANES + k for k in lower])
            pick_upper = ir.Constant(ir.VectorType(i32, LANES), upper + [LANES + k for k in upper])
            values = [
                builder.fadd(builder.shuffle_vector(a, b, pick_lower), builder.shuffle_vector(a, b, pick_upper))
                for a, b in zip(values[0::2], values[1::2])
            ]
            group = half
        return values[0]

    return vec(vectors), codegen


@intrinsic
def lane(typingctx, value, j):
    """Lane j of a Vec, as a scalar."""
    if not isinstance(value, Vec):
        raise TypingError(f"lane({value}, {j})")

    def codegen(context, builder, signature, args):
        index = builder.trunc(args[1], ir.IntType(32)) if args[1].type.width > 32 else args[1]
        return builder.extract_element(args[0], index)

    return value.dtype(value, j), codegen


def _masked(builder, n):
    """The lane mask `lane < n` (n an i64) for LLVM's masked loads and stores."""
    i32 = ir.IntType(32)
    lanes = ir.Constant(ir.VectorType(i32, LANES), list(range(LANES)))
    bound = _splat(builder, builder.trunc(n, i32), ir.VectorType(i32, LANES))
    return builder.icmp_signed("<", lanes, bound)


def _masked_name(kind, vector_type):
    element = {"float": "f32", "double": "f64", "i32": "i32"}[str(vector_type.element)]
    return f"llvm.masked.{kind}.v{LANES}{element}.p0"


@intrinsic
def load_first(typingctx, array, row, col, n):
    """array[row, col:col + n] in the first n lanes, 0 in the others (a masked load: nothing past
    the n elements is read, so a row's last, partial chunk is safe)."""
    _check_rows(array)
    vec = Vec(array.dtype)

    def codegen(context, builder, signature, args):
        vector_type = _vector_type(context, array.dtype)
        pointer = builder.bitcast(
            _pointer(context, builder, array, args[0], args[1], args[2]), vector_type.as_pointer()
        )
        mask = _masked(builder, args[3])
        zero = ir.Constant(vector_type, [ir.Constant(vector_type.element, 0)] * LANES)
        i32 = ir.IntType(32)
        function_type = ir.FunctionType(vector_type, [pointer.type, i32, mask.type, vector_type])
        fn = cgutils.get_or_insert_function(builder.module, function_type, _masked_name("load", vector_type))
        align = context.get_abi_sizeof(context.get_value_type(array.dtype))
        return builder.call(fn, [pointer, i32(align), mask, zero])

    return vec(array, row, col, n), codegen


@intrinsic
def store_first(typingctx, array, row, col, value, n):
    """array[row, col:col + n] = the first n lanes of value (a masked store)."""
    _check_rows(array)
    if not (isinstance(value, Vec) and value.dtype == array.dtype):
        raise TypingError(f"cannot store {value} into {array}")

    def codegen(context, builder, signature, args):
        vector_type = _vector_type(context, array.dtype)
        pointer = builder.bitcast(
            _pointer(context, builder, array, args[0], args[1], args[2]), vector_type.as_pointer()
        )
        mask = _masked(builder, args[4])
        i32 = ir.IntType(32)
        function_type = ir.FunctionType(ir.VoidType(), [vector_type, pointer.type, i32, mask.type])
        fn = cgutils.get_or_insert_function(builder.module, function_type, _masked_name("store", vector_type))
        align = context.get_abi_sizeof(context.get_value_type(array.dtype))
        builder.call(fn, [args[3], pointer, i32(align), mask])
        return context.get_dummy_value()

    return types.void(array, row, col, value, n), codegen
