"""Deterministic procedural miniature rooms rendered by exact ray casting (see ``writer``)."""

from usvc.synth.params import RoomParams, validate
from usvc.synth.room import Layout, make_layout
from usvc.synth.trajectory import Sequence, make_sequences
from usvc.synth.writer import Renderer, generate_scene, intrinsics

__all__ = [
    "Layout",
    "Renderer",
    "RoomParams",
    "Sequence",
    "generate_scene",
    "intrinsics",
    "make_layout",
    "make_sequences",
    "validate",
]
