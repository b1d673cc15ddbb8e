"""The type stubs describe the module as built: every public name and method is in
`_tcsense.pyi`, and nothing there is missing from the module."""

import ast
import inspect
import pathlib

import tcsense
import tcsense._tcsense as native

STUB = pathlib.Path(tcsense.__file__).with_name("_tcsense.pyi")


def stub_names():
    tree = ast.parse(STUB.read_text())
    top, members = set(), {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            top.add(node.name)
        elif isinstance(node, (ast.AnnAssign,)) and isinstance(node.target, ast.Name):
            top.add(node.target.id)
        if isinstance(node, ast.ClassDef):
            members[node.name] = {n.name for n in node.body if isinstance(n, ast.FunctionDef)}
    return top, members


def test_stub_covers_the_module():
    top, members = stub_names()
    public = {n for n in dir(native) if not n.startswith("_")} - {"ItemIter"}
    assert public - top == set(), "in the module but not in the stub"
    assert set(tcsense.__all__) - top == set()
    for cls, names in members.items():
        if cls == "TcsenseError":
            continue
        obj = getattr(native, cls)
        runtime = {n for n, _ in inspect.getmembers(obj) if not n.startswith("_")}
        assert runtime - names == set(), f"{cls}: in the module but not in the stub"
        assert {n for n in names if not n.startswith("_")} - runtime == set(), f"{cls}: in the stub but not in the module"


def test_every_public_call_has_a_docstring():
    for name in tcsense.__all__:
        obj = getattr(tcsense, name)
        if callable(obj):
            assert (obj.__doc__ or "").strip(), name
