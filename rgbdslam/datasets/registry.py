"""The table of sequence readers: each source's module declares itself with :func:`reader`.

``rgbdslam.datasets.open_sequence`` loads the built-in readers and asks each, in the order they
were declared, whether it recognises a folder. (This module imports no reader, so the readers
can import it without an import cycle.)
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable

from rgbdslam.datasets.base import Sequence

# name -> (detect(path) -> bool, factory(path, dataset_config) -> Sequence), in declaration order
READERS: dict[str, tuple[Callable[[Path], bool], Callable[..., Sequence]]] = {}


def reader(name: str, detect: Callable[[Path], bool], before: str | None = None):
    """Class decorator: the sequence reader for ``dataset.kind = name``; ``detect(folder)`` says
    whether a folder is in its layout (for ``kind: auto``). ``before``: a reader whose layout this
    one's is a special case of (ICL-NUIM's of TUM's): this one is asked first."""
    def deco(factory: Callable[..., Sequence]):
        READERS[name] = (detect, factory)
        if before in READERS:
            keys = list(READERS)
            for other in keys[keys.index(before):]:
                if other != name:
                    READERS[other] = READERS.pop(other)  # ``before`` and those after it go behind ``name``
        return factory

    return deco
