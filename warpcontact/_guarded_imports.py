"""Third-party packages imported before the rest of the package, with a Ctrl-C held back.

trimesh's optional imports catch every exception, KeyboardInterrupt included: a Ctrl-C
while Python imported it was lost, and a command ran on and replaced its earlier results (a
probe, stop 64). Imported here first, the interruption is raised once the import is done.
"""

from ._files import interrupts_held

with interrupts_held() as interrupted:
    import trimesh  # noqa: F401
if interrupted:
    raise KeyboardInterrupt
