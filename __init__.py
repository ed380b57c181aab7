"""ArtNVG node pack for ComfyUI (classic API): ComfyUI reads the two mappings below.

The nodes import the pack's library ``artnvg_core``; when it is not installed as a
package, it is loaded from this folder (only that package is exposed, not the folder).
"""

import importlib.util
import os
import sys

if importlib.util.find_spec("artnvg_core") is None:
    _core = os.path.join(os.path.dirname(os.path.abspath(__file__)), "artnvg_core")
    _spec = importlib.util.spec_from_file_location(
        "artnvg_core", os.path.join(_core, "__init__.py"), submodule_search_locations=[_core]
    )
    _module = importlib.util.module_from_spec(_spec)
    sys.modules["artnvg_core"] = _module
    try:
        _spec.loader.exec_module(_module)
    except BaseException:
        del sys.modules["artnvg_core"]
        raise

# ComfyUI imports this folder as a package. pytest imports this file alone, as a plain module
# named __init__, when the folder's name is not an identifier (custom_nodes/artnvg-comfyui): it
# collects every folder holding an __init__.py as a test package. There is no pack to load then.
if __package__:
    from .nodes import NODE_CLASS_MAPPINGS, NODE_DISPLAY_NAME_MAPPINGS

    __all__ = ["NODE_CLASS_MAPPINGS", "NODE_DISPLAY_NAME_MAPPINGS"]
