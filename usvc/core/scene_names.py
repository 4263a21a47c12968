"""What a scene may be called: the one rule `usvc map --name` and every stage's `scene.name` obey."""

from __future__ import annotations

import keyword
import re

# What a scene may be called: the one rule `usvc map --name` and every stage's `scene.name` obey. The
# name is a folder (data/<name>/, results/<name>/, data/raw/<name>), a config name
# (conf/scene/<name>.yaml, `scene=<name>`) and an entry of params.yaml.
SCENE_NAME_RULE = re.compile(r"^[a-z][a-z0-9_]{0,63}$")
# Words a scene name must not be: Python keywords (the name is used as an identifier by tools that
# read params), YAML/OmegaConf literals (`scene=null` deletes the group, `name: yes` is a boolean),
# Hydra's own keys, and `raw` (data/raw/ holds every scene's photos, data/<name>/ its artifacts).
RESERVED_SCENE_NAMES = {
    **{w: "a Python keyword" for w in keyword.kwlist if w.islower()},
    **{w: "a YAML/Hydra literal" for w in ("null", "none", "true", "false", "yes", "no", "on", "off", "nan", "inf")},
    **{w: "a Hydra key" for w in ("hydra", "defaults")},
    "raw": "data/raw/ holds the scenes' photos",
}


def scene_name_problem(name: object) -> str:
    """Why `name` cannot be a scene's name ("" when it can): it must match SCENE_NAME_RULE (so no
    `..`, `/`, `\\`, nothing empty: it names folders), be none of RESERVED_SCENE_NAMES and not start
    with `base_` (conf/scene/base_scene is the schema every scene builds on)."""
    if not isinstance(name, str) or not SCENE_NAME_RULE.fullmatch(name):  # fullmatch: not even a trailing newline
        return "use lower-case letters, digits and _, starting with a letter (at most 64 characters)"
    if name in RESERVED_SCENE_NAMES:
        return f"is reserved ({RESERVED_SCENE_NAMES[name]})"
    if name.startswith("base_"):
        return ("names starting with base_ are reserved for usvc's config schemas "
                "(conf/scene/base_scene would replace the schema every scene builds on)")
    return ""
