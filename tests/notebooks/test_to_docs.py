"""notebooks/to_docs.py writes an executed notebook as Markdown: cells in order, stdout kept,
stderr (progress bars) dropped, pictures written as PNG files and linked."""

from __future__ import annotations

import base64
import importlib.util
from pathlib import Path

import nbformat

SCRIPT = Path(__file__).resolve().parents[2] / "notebooks" / "to_docs.py"
PNG = base64.b64decode(
    "iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg==")


def _to_docs():
    spec = importlib.util.spec_from_file_location("to_docs", SCRIPT)
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_an_executed_notebook_becomes_markdown_with_its_pictures(tmp_path):
    v4 = nbformat.v4
    nb = v4.new_notebook(cells=[
        v4.new_markdown_cell("# Title"),
        v4.new_code_cell("print('hi')", outputs=[
            v4.new_output("stream", name="stdout", text="hi\n"),
            v4.new_output("stream", name="stderr", text="progress 10%\r"),
            v4.new_output("display_data", data={"image/png": base64.b64encode(PNG).decode(), "text/plain": "<Figure>"}),
            v4.new_output("execute_result", data={"text/plain": "42"}, execution_count=1),
        ]),
        v4.new_code_cell("   "),
    ])
    md = _to_docs().to_markdown(nb, "book", tmp_path)
    assert md.index("# Title") < md.index("```python\nprint('hi')\n```") < md.index("hi") < md.index("![output 1]")
    assert "progress" not in md and "<Figure>" not in md and md.rstrip().endswith("42\n```")
    assert "![output 1](book/01.png)" in md
    assert (tmp_path / "01.png").read_bytes() == PNG
    assert md.count("```python") == 1  # the blank cell is left out
