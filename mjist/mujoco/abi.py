"""MuJoCo's C ABI as the collision hook needs it: the library, its collision table, the
``mjData`` field offsets, and the numba intrinsics that read raw memory and call C pointers.

Everything here was checked against MuJoCo 4.0 (see ``../shared/notes`` in the project
history): ``mjCOLLISIONFUNC`` is a public writable ``[mjNGEOMTYPES][mjNGEOMTYPES]`` table of
``int f(const mjModel*, mjData*, mjPreContact*, int g1, int g2, mjtNum margin)``, and
``mjPreContact`` is ten doubles (dist, pos[3], normal[3], tangent[3]).

The hook finds its data through one process-wide word, ``mjist_registry_v1``, registered
with LLVM's symbol table at import: compiled (and cached) code refers to it by name, so the
cached machine code stays valid from one process to the next.
"""
from __future__ import annotations

import ctypes
import glob
import os

import llvmlite.binding as llvm
import mujoco
import numpy as np
from llvmlite import ir
from mujoco.introspect import structs as _mj_structs
from numba import types
from numba.extending import intrinsic

VERIFIED_VERSIONS = ("4.0",)  # struct layout and table facts measured on these
NGEOMTYPES = int(mujoco.mjtGeom.mjNGEOMTYPES)
GEOM_PLANE = int(mujoco.mjtGeom.mjGEOM_PLANE)
GEOM_SPHERE = int(mujoco.mjtGeom.mjGEOM_SPHERE)
GEOM_CAPSULE = int(mujoco.mjtGeom.mjGEOM_CAPSULE)
GEOM_BOX = int(mujoco.mjtGeom.mjGEOM_BOX)
GEOM_MESH = int(mujoco.mjtGeom.mjGEOM_MESH)
GEOM_SDF = int(mujoco.mjtGeom.mjGEOM_SDF)
PRECONTACT_DOUBLES = 10  # dist, pos[3], normal[3], tangent[3]

REGISTRY_SYMBOL = "mjist_registry_v1"
# the cell holds the address of the current registry root array (0: nothing attached)
_CELL = ctypes.c_int64(0)
llvm.add_symbol(REGISTRY_SYMBOL, ctypes.addressof(_CELL))


class MuJoCoABIError(RuntimeError):
    """This MuJoCo build does not match the layout the hook was verified against."""


def check_version():
    """Refuse MuJoCo versions whose struct layout was not verified."""
    ver = mujoco.__version__
    if not any(ver == v or ver.startswith(v + ".") for v in VERIFIED_VERSIONS):
        raise MuJoCoABIError(
            f"mjist's collision hook was verified on MuJoCo {', '.join(VERIFIED_VERSIONS)}.x, this is {ver}: "
            "install mujoco>=4.0,<4.1 (pip install 'mujoco~=4.0.0') or re-verify mjist/mujoco/abi.py for this version"
        )


_LIB = None


def lib() -> ctypes.CDLL:
    """The ``libmujoco`` already loaded by the ``mujoco`` package."""
    global _LIB
    if _LIB is None:
        here = os.path.dirname(mujoco.__file__)
        cands = sorted(glob.glob(os.path.join(here, "libmujoco.so*")) + glob.glob(os.path.join(here, "libmujoco*.dylib"))
                       + glob.glob(os.path.join(here, "mujoco*.dll")))
        if not cands:
            raise MuJoCoABIError(f"libmujoco not found next to the mujoco package ({here}): reinstall mujoco from pip")
        _LIB = ctypes.CDLL(cands[0])
    return _LIB


def fn_address(name: str) -> int:
    """Address of an exported libmujoco function."""
    return int(ctypes.cast(getattr(lib(), name), ctypes.c_void_p).value)


def collision_table():
    """The writable ``mjCOLLISIONFUNC`` table as a flat ctypes array (row-major, type1 <= type2)."""
    return (ctypes.c_void_p * (NGEOMTYPES * NGEOMTYPES)).in_dll(lib(), "mjCOLLISIONFUNC")


def table_index(t1: int, t2: int) -> int:
    a, b = min(t1, t2), max(t1, t2)
    return a * NGEOMTYPES + b


# --------------------------------------------------------------------------- mjData offsets

_PROBE_XML = """
<mujoco>
  <worldbody>
    <body><freejoint/><geom type="box" size=".1 .1 .1"/><site/></body>
    <body pos="0 0 1"><joint type="hinge"/><geom type="sphere" size=".1"/>
      <geom type="capsule" size=".1 .2" pos=".3 0 0"/></body>
    <body mocap="true" pos="0 0 2"><geom type="sphere" size=".1" contype="0" conaffinity="0"/></body>
  </worldbody>
</mujoco>
"""
# fields the hook reads: pointers to mjData's arrays, the simulation time and the arena counters
_POINTER_FIELDS = ("geom_xpos", "geom_xmat", "xpos", "xquat", "xipos", "mocap_pos", "mocap_quat", "qfrc_passive")
_OFFSETS: dict | None = None

# size and alignment (bytes) of the C types mjData's declaration uses, on the 64-bit ABIs
# MuJoCo ships for (x86-64, AArch64: LP64); its own structs are laid out from their fields
_C_TYPES = {"char": 1, "unsigned char": 1, "mjtByte": 1, "mjtBool": 1, "short": 2, "int": 4, "unsigned int": 4,
            "float": 4, "mjtNum": 8, "double": 8, "size_t": 8, "uintptr_t": 8, "mjtSize": 8, "int64_t": 8,
            "uint64_t": 8}


def _type_layout(t) -> tuple[int, int]:
    """``(size, alignment)`` of an introspected C type (C layout rules)."""
    from mujoco.introspect import ast_nodes as A

    if isinstance(t, A.PointerType):
        return 8, 8
    if isinstance(t, A.ArrayType):
        size, align = _type_layout(t.inner_type)
        return size * int(np.prod(t.extents)), align
    if isinstance(t, A.ValueType):
        if t.name in _C_TYPES:
            return _C_TYPES[t.name], _C_TYPES[t.name]
        if t.name in _mj_structs.STRUCTS:
            _, size, align = struct_layout(t.name)
            return size, align
        if t.name.startswith("mjt"):  # an enum
            return 4, 4
    raise MuJoCoABIError(f"mjData declares a field of type {t!r} whose size mjist does not know: use MuJoCo 4.0")


def struct_layout(name: str) -> tuple[dict, int, int]:
    """Byte offset of each field of MuJoCo struct ``name`` from its declaration (MuJoCo's
    introspection: field order and types), the struct's size and its alignment."""
    offsets, at, align = {}, 0, 1
    for f in _mj_structs.STRUCTS[name].fields:
        size, a = _type_layout(f.type)
        at = -(-at // a) * a
        offsets[f.name] = at
        at += size
        align = max(align, a)
    return offsets, -(-at // align) * align, align


def _words(address: int, n: int) -> np.ndarray:
    return np.frombuffer((ctypes.c_uint64 * n).from_address(address), dtype=np.uint64).copy()


def _check(words: np.ndarray, d, off: dict) -> None:
    """Verify the offsets ``off`` by value against ``d`` (an ``MjData``) whose memory, from its
    start to the end of the struct, is ``words``; raise naming the first field that differs."""
    for name in _POINTER_FIELDS:
        arr = getattr(d, name)
        if arr.size and int(words[off[name] // 8]) != arr.ctypes.data:
            raise MuJoCoABIError(f"mjData.{name} is not at byte {off[name]}, where MuJoCo's declaration of mjData puts it: "
                                 "this MuJoCo build's struct layout differs from its headers; use MuJoCo 4.0 from pip")
    if words[off["time"] // 8] != np.array([d.time]).view(np.uint64)[0]:
        raise MuJoCoABIError(f"mjData.time is not at byte {off['time']}, where MuJoCo's declaration of mjData puts it: "
                             "use MuJoCo 4.0 from pip")
    for name in ("narena", "pstack", "parena"):
        if int(words[off[name] // 8]) != int(getattr(d, name)):
            raise MuJoCoABIError(f"mjData.{name} is not at byte {off[name]}, where MuJoCo's declaration of mjData puts it: "
                                 "use MuJoCo 4.0 from pip")


def data_offsets() -> dict:
    """Byte offsets inside ``mjData`` of the fields the hook reads.

    Computed from the struct's declaration (field order and types from MuJoCo's introspection,
    laid out by C rules) and verified once by value on a probe ``MjData`` whose every probed
    array is non-empty; reads never go past ``sizeof(mjData)``.
    """
    global _OFFSETS
    if _OFFSETS is None:
        check_version()
        layout, size, _ = struct_layout("mjData")
        off = {k: layout[k] for k in (*_POINTER_FIELDS, "time", "narena", "pstack", "parena", "threadpool")}
        m = mujoco.MjModel.from_xml_string(_PROBE_XML)
        d = mujoco.MjData(m)
        d.time = 1234.5678125  # an exactly representable, unlikely value
        _check(_words(d._address, size // 8), d, off)
        off["sizeof"] = size
        _OFFSETS = off
    return dict(_OFFSETS)


def verify_offsets(d: mujoco.MjData, off: dict) -> None:
    """Check the offsets on a real ``MjData`` (refuse to run on a mismatch, naming the field)."""
    _check(_words(d._address, off["sizeof"] // 8), d, off)


# --------------------------------------------------------------------------- numba intrinsics
# Raw memory and C calls from nopython code; each is a few LLVM instructions.

_I64 = ir.IntType(64)
_I32 = ir.IntType(32)
_F64 = ir.DoubleType()


@intrinsic
def registry_root(typingctx):
    """Address of the registry root array (the word behind ``mjist_registry_v1``)."""
    def codegen(context, builder, signature, args):
        mod = builder.module
        gv = mod.globals.get(REGISTRY_SYMBOL)
        if gv is None:
            gv = ir.GlobalVariable(mod, _I64, REGISTRY_SYMBOL)
            gv.linkage = "external"
        return builder.load(gv)
    return types.int64(), codegen


@intrinsic
def i64_ptr(typingctx, addr):
    """``int64*`` from an integer address."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], _I64.as_pointer())
    return types.CPointer(types.int64)(types.int64), codegen


@intrinsic
def f64_ptr(typingctx, addr):
    """``double*`` from an integer address."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], _F64.as_pointer())
    return types.CPointer(types.float64)(types.int64), codegen


@intrinsic
def i32_ptr(typingctx, addr):
    """``int32*`` from an integer address."""
    def codegen(context, builder, signature, args):
        return builder.inttoptr(args[0], ir.IntType(32).as_pointer())
    return types.CPointer(types.int32)(types.int64), codegen


@intrinsic
def load_i64(typingctx, addr):
    """The 64-bit word at ``addr``."""
    def codegen(context, builder, signature, args):
        return builder.load(builder.inttoptr(args[0], _I64.as_pointer()))
    return types.int64(types.int64), codegen


@intrinsic
def load_f64(typingctx, addr):
    """The double at ``addr``."""
    def codegen(context, builder, signature, args):
        return builder.load(builder.inttoptr(args[0], _F64.as_pointer()))
    return types.float64(types.int64), codegen


@intrinsic
def cas_i64(typingctx, addr, expected, new):
    """Atomic compare-and-swap of the word at ``addr``; returns the value found there."""
    def codegen(context, builder, signature, args):
        ptr = builder.inttoptr(args[0], _I64.as_pointer())
        res = builder.cmpxchg(ptr, args[1], args[2], "seq_cst", "seq_cst")
        return builder.extract_value(res, 0)
    return types.int64(types.int64, types.int64, types.int64), codegen


@intrinsic
def call_stack_alloc(typingctx, fn, d, nbytes, align):
    """``mj_stackAllocByte(d, nbytes, align)`` through its address; returns the address."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(_I64, [_I64, _I64, _I64])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        return builder.call(f, [args[1], args[2], args[3]])
    return types.int64(types.int64, types.int64, types.int64, types.int64), codegen


@intrinsic
def call_with_data(typingctx, fn, d):
    """``fn(d)`` for ``void fn(mjData*)`` (``mj_markStack``, ``mj_freeStack``)."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_I64])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [args[1]])
        return context.get_dummy_value()
    return types.none(types.int64, types.int64), codegen


@intrinsic
def call_collision(typingctx, fn, m, d, con, g1, g2, margin):
    """Call a collision function pointer (MuJoCo's original, for pairs the IST does not manage)."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(_I32, [_I64, _I64, _I64, _I32, _I32, _F64])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        return builder.call(f, list(args[1:]))
    sig = types.int32(types.int64, types.int64, types.int64, types.int64, types.int32, types.int32, types.float64)
    return sig, codegen


@intrinsic
def call_apply_ft(typingctx, fn, m, d, force, torque, point, body, qfrc):
    """``mj_applyFT(m, d, force, torque, point, body, qfrc_target)`` (pointers as int64)."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_I64, _I64, _I64, _I64, _I64, _I32, _I64])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, list(args[1:]))
        return context.get_dummy_value()
    sig = types.none(types.int64, types.int64, types.int64, types.int64, types.int64, types.int64, types.int32, types.int64)
    return sig, codegen


@intrinsic
def call_object_velocity(typingctx, fn, m, d, objtype, objid, res, flg_local):
    """``mj_objectVelocity(m, d, objtype, objid, res[6], flg_local)``: angular then linear velocity."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_I64, _I64, _I32, _I32, _I64, _I32])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, list(args[1:]))
        return context.get_dummy_value()
    sig = types.none(types.int64, types.int64, types.int64, types.int32, types.int32, types.int64, types.int32)
    return sig, codegen


@intrinsic
def call_generic(typingctx, fn, m, d):
    """``fn(m, d)`` for an ``mjfGeneric`` callback (the previous ``mjcb_passive``)."""
    def codegen(context, builder, signature, args):
        fnty = ir.FunctionType(ir.VoidType(), [_I64, _I64])
        f = builder.inttoptr(args[0], fnty.as_pointer())
        builder.call(f, [args[1], args[2]])
        return context.get_dummy_value()
    return types.none(types.int64, types.int64, types.int64), codegen


def passive_callback():
    """The ``mjcb_passive`` global of libmujoco (a ctypes ``c_void_p``)."""
    return ctypes.c_void_p.in_dll(lib(), "mjcb_passive")


def set_registry(address: int) -> None:
    """Point the hook at a new registry root (one aligned 8-byte store: atomic for readers)."""
    _CELL.value = int(address)
