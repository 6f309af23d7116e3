"""A small XML reader that keeps the line of every element.

xml.etree drops line numbers; expat reports them while it parses, so elements
are built here directly from expat callbacks. Malformed XML raises a
SceneError carrying expat's line.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from xml.parsers import expat

from mpg.errors import SceneError


@dataclass
class Node:
    tag: str
    attrib: dict[str, str]
    line: int
    file: str
    children: list[Node] = field(default_factory=list)

    def get(self, key: str, default: str | None = None) -> str | None:
        return self.attrib.get(key, default)

    def error(self, message: str) -> SceneError:
        return SceneError(message, self.file, self.line)

    def describe(self) -> str:
        t = self.attrib.get("type")
        n = self.attrib.get("name")
        s = f"<{self.tag}"
        if t is not None:
            s += f' type="{t}"'
        if n is not None:
            s += f' name="{n}"'
        return s + ">"


def parse_xml(data: str | bytes, filename: str) -> Node:
    """Parse a whole document, returning its root element."""
    parser = expat.ParserCreate()
    stack: list[Node] = []
    root: list[Node] = []

    def start(tag: str, attrs: dict[str, str]) -> None:
        node = Node(tag, dict(attrs), parser.CurrentLineNumber, filename)
        if stack:
            stack[-1].children.append(node)
        else:
            root.append(node)
        stack.append(node)

    def end(tag: str) -> None:
        stack.pop()

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    try:
        parser.Parse(data, True)
    except expat.ExpatError as e:
        raise SceneError(f"malformed XML: {expat.ErrorString(e.code)}", filename, e.lineno) from None
    except (ValueError, UnicodeError) as e:
        raise SceneError(f"malformed XML: {e}", filename, getattr(parser, "CurrentLineNumber", None)) \
            from None
    if not root:
        raise SceneError("empty XML document", filename, 1)
    return root[0]
