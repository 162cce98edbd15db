"""The reports' and sweeps' matplotlib figures, written so that no reader sees half a file."""

from __future__ import annotations

from pathlib import Path


def save_figure(fig, path: Path) -> None:
    """Lay out, write atomically (a temp file renamed: a reader never sees half a PNG) and close."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp.png")
    fig.savefig(tmp)
    plt.close(fig)
    tmp.replace(path)
