"""What a dataset layout checker reports: files present, problems found, class histogram."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path


@dataclass(frozen=True)
class Problem:
    """One thing missing or malformed.

    Attributes:
        path: the file or folder concerned.
        frame: the frame id it belongs to, or None.
        expected: what the layout requires there.
        found: what is there instead.
    """

    path: str
    frame: str | None
    expected: str
    found: str

    def __str__(self) -> str:
        where = f"{self.path}" + (f" (frame {self.frame})" if self.frame is not None else "")
        return f"{where}: expected {self.expected}, found {self.found}"


@dataclass
class LayoutReport:
    """Result of walking a dataset folder against a layout.

    Attributes:
        layout: layout name (``replica``, ``replica_instance``, ``scannet``).
        root: the folder checked.
        present: counts of what was found, by kind (``scenes``, ``rgb``, ``depth``, ...).
        problems: everything missing or malformed.
        class_histogram: pixel count per class name (after the layout's label mapping; ``ignore`` included).
        notes: informational lines (e.g. frames dropped for invalid poses).
    """

    layout: str
    root: Path
    present: dict[str, int] = field(default_factory=dict)
    problems: list[Problem] = field(default_factory=list)
    class_histogram: dict[str, int] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.problems

    def format(self, max_problems: int = 50) -> str:
        lines = [f"layout {self.layout} at {self.root}"]
        lines += ["present:"] + [f"  {kind}: {count}" for kind, count in self.present.items()]
        lines += [f"note: {note}" for note in self.notes]
        if self.problems:
            lines.append(f"problems ({len(self.problems)}):")
            lines += [f"  {problem}" for problem in self.problems[:max_problems]]
            if len(self.problems) > max_problems:
                lines.append(f"  ... and {len(self.problems) - max_problems} more")
        else:
            lines.append("problems: none")
        if self.class_histogram:
            total = sum(self.class_histogram.values()) or 1
            lines.append("class histogram (pixels):")
            for name, count in sorted(self.class_histogram.items(), key=lambda item: -item[1]):
                lines.append(f"  {name:<24} {count:>12}  {100.0 * count / total:6.2f}%")
        return "\n".join(lines)
