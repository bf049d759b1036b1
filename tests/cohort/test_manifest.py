"""A cohort's input refused with the problem and its fix named (no Ray needed)."""
import pytest

from mjist.cohort import discover


@pytest.mark.parametrize("text,message", [
    ("folder\nx\n", r"needs a 'patient' column \(and folder, or maxilla \+ mandible; optional .*hinge"),
    ("patient,folder\n ,x\n", r"row 2: empty patient id"),
    ("patient,folder\na,x\na,y\n", r"patient 'a' appears twice"),
    ("patient,folder,hinge\na,x,1 2 z\n", r"patient 'a': hinge must be three numbers 'x y z'"),
    ("patient,folder,hinge\na,x,1 2\n", r"patient 'a': hinge must be three numbers 'x y z' \(got 2 numbers\)"),
    ("patient,maxilla\na,up.stl\n", r"patient 'a': give a folder, or both maxilla and mandible"),
])
def test_bad_manifest_rows_are_named(tmp_path, text, message):
    m = tmp_path / "cohort.csv"
    m.write_text(text)
    with pytest.raises(ValueError, match=message):
        discover(m)


def test_missing_or_empty_input_says_what_to_give(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist: give a folder of patient folders or a manifest CSV"):
        discover(tmp_path / "nothing")
    with pytest.raises(ValueError, match=r"holds no patient folders \(each with a maxilla and a mandible mesh\)"):
        discover(tmp_path)
