"""The role of an exported object (dynamic / static / skipped) and the reason codes behind it.

One role per object replaces separate flags: control flow reads the Reason code, never the words
(`SceneObject.why`), which are for report.json and the CLI. report.json keeps its keys: "static"
(role static), "static_reason" (why, for a static object other than the environment) and
"skipped" (why, for a skipped one).
"""
from __future__ import annotations

from enum import Enum


class Role(str, Enum):
    """What an exported object is in the simulation."""

    DYNAMIC = "dynamic"     # a rigid body: freejoint (MJCF), RigidBodyAPI + MassAPI (USD)
    STATIC = "static"       # a collider welded to the world: no joint, no mass
    SKIPPED = "skipped"     # not exported (reported in report.json's "skipped" with the reason)


class Reason(str, Enum):
    """Why an object is not a dynamic rigid body (the code; SceneObject.why says it in words)."""

    # static
    ENVIRONMENT = "environment"             # the background: floor, walls, unlabelled surfaces
    STATIC_CLASS = "static_class"           # heavy furniture (exporters.physics.STATIC_CLASSES)
    LITTLE_EVIDENCE = "little_evidence"     # fewer checkpoint surfels than a rigid body needs
    UNSTABLE = "unstable"                   # moved or fell in the settle check: pinned
    # skipped
    NO_SURFACE = "no_surface"               # nothing fused for the instance
    REPAIR = "repair"                       # could not be made a sound solid
    ROOM_SIZED = "room_sized"               # wider than any movable object: left to the background
    SWALLOWED = "swallowed"                 # (almost) nothing left after a floor / overlap cut
    DECIMATION = "decimation"               # decimation lost watertightness
    PHYSICS = "physics"                     # no mass properties (no volume)

