"""The host link parses an EDS once per file version and node id (several ms each time otherwise)."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import canopen

from dob_hil.link.cia402 import link as cia402_link
from dob_hil.link.cia402.options import DEFAULT_EDS


def test_the_same_file_and_node_parse_once(tmp_path: Path) -> None:
    eds = tmp_path / "drive.eds"
    shutil.copyfile(DEFAULT_EDS, eds)
    first = cia402_link._object_dictionary(eds, 5)
    assert cia402_link._object_dictionary(eds, 5) is first
    other_node = cia402_link._object_dictionary(eds, 6)
    assert other_node is not first
    # $NODEID resolved per node: the TPDO1 COB-ID default follows the node id
    assert first[0x1800][1].default != other_node[0x1800][1].default


def test_an_edited_file_is_parsed_again(tmp_path: Path) -> None:
    eds = tmp_path / "drive.eds"
    shutil.copyfile(DEFAULT_EDS, eds)
    before = cia402_link._object_dictionary(eds, 5)
    text = eds.read_text().replace("ProductName=", "ProductName=Edited ", 1)
    eds.write_text(text)
    st = eds.stat()
    os.utime(eds, ns=(st.st_atime_ns, st.st_mtime_ns + 1_000_000_000))  # a later version
    after = cia402_link._object_dictionary(eds, 5)
    assert after is not before
    assert isinstance(after, canopen.ObjectDictionary)


def test_a_same_size_copy_with_the_old_mtime_is_parsed_again(tmp_path: Path) -> None:
    """cp -p / shutil.copy2 / rsync -t keep the modification time: the change time or inode moves."""
    eds = tmp_path / "drive.eds"
    shutil.copyfile(DEFAULT_EDS, eds)
    before = cia402_link._object_dictionary(eds, 5)
    text = eds.read_text()
    edited = text.replace("ProductName=Generic", "ProductName=Genera1", 1)
    assert len(edited) == len(text) and edited != text
    other = tmp_path / "other.eds"
    other.write_text(edited)
    st = eds.stat()
    os.utime(other, ns=(st.st_atime_ns, st.st_mtime_ns))
    os.replace(other, eds)
    assert eds.stat().st_mtime_ns == st.st_mtime_ns and eds.stat().st_size == st.st_size
    after = cia402_link._object_dictionary(eds, 5)
    assert after is not before
