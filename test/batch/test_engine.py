"""The batch engine: the local cluster listens on the loopback only; inputs and names; the import graph."""

from __future__ import annotations

import ast
import os
import socket
from pathlib import Path

import pytest

from selfcontra_ros.batch.inputs import expand_inputs, input_name
from selfcontra_ros.datasets.synthetic import write_sequence
from selfcontra_ros.errors import BatchError

PACKAGE = Path(__file__).resolve().parents[2] / "selfcontra_ros"


def _socket_inodes(pids: set[int]) -> set[str]:
    inodes = set()
    for pid in pids:
        try:
            for fd in (Path("/proc") / str(pid) / "fd").iterdir():
                target = str(fd.readlink())
                if target.startswith("socket:["):
                    inodes.add(target[len("socket:[") : -1])
        except OSError:  # a process that ended meanwhile
            continue
    return inodes


def _address(field: str, ipv6: bool) -> str:
    address = bytes.fromhex(field.split(":")[0])
    if ipv6:  # /proc writes each 32-bit word in host (little-endian) order
        return socket.inet_ntop(socket.AF_INET6, b"".join(address[i : i + 4][::-1] for i in range(0, 16, 4)))
    return socket.inet_ntop(socket.AF_INET, address[::-1])


def _sockets(inodes: set[str]) -> list[tuple[str, str, str]]:
    """(table, local address, remote address) of the TCP/UDP sockets with these inodes (/proc/net)."""
    found = []
    for table, ipv6 in (("tcp", False), ("tcp6", True), ("udp", False), ("udp6", True)):
        for line in (Path("/proc/net") / table).read_text().splitlines()[1:]:
            fields = line.split()
            if fields[9] in inodes:
                found.append((table, _address(fields[1], ipv6), _address(fields[2], ipv6)))
    return found


def test_the_local_cluster_listens_on_the_loopback_only(ray_cluster: set[int]) -> None:
    import ray

    assert str(ray.get_runtime_context().gcs_address).startswith("127.0.0.1:")
    assert {node["NodeManagerAddress"] for node in ray.nodes()} == {"127.0.0.1"}
    assert os.environ["RAY_USAGE_STATS_ENABLED"] == "0"
    sockets = _sockets(_socket_inodes(ray_cluster))
    assert len(sockets) >= 3  # GCS, raylet, workers: the check sees them
    loopback = {"127.0.0.1", "::ffff:127.0.0.1", "::1"}
    bound = [(t, local) for t, local, _ in sockets if local not in loopback]
    assert bound == [], f"Ray binds beyond the loopback: {bound}"
    peers = [(t, peer) for t, _, peer in sockets if peer not in loopback | {"0.0.0.0", "::"}]
    assert peers == [], f"Ray talks to another machine: {peers}"


def test_inputs_are_expanded_and_named(tmp_path: Path) -> None:
    fleet = tmp_path / "fleet"
    for name in ("a", "b"):
        write_sequence(tmp_path / "one" / name, scene="street", frames=2, width=64, height=32, seed=1)
    root = tmp_path / "one" / "a"
    (root / "sequences" / "00").rename(root / "sequences" / "07")
    (root / "poses" / "00.txt").rename(root / "poses" / "07.txt")
    write_sequence(fleet, scene="street", frames=2, width=64, height=32, seed=1)
    (fleet / "sequences" / "00").rename(fleet / "sequences" / "03")
    write_sequence(tmp_path / "two", scene="street", frames=2, width=64, height=32, seed=1)
    (tmp_path / "two" / "sequences" / "00").rename(fleet / "sequences" / "04")
    bag = tmp_path / "drive.mcap"
    bag.write_bytes(b"not really a bag")

    assert input_name(root) == "a_07" and input_name(root / "sequences" / "07") == "a_07"
    assert input_name(bag) == "drive"
    found = expand_inputs([str(tmp_path / "one" / "*"), str(fleet), str(bag), str(root / "sequences" / "07")])
    assert [(i.name, i.kind) for i in found] == [
        ("a_07", "sequence"),
        ("b_00", "sequence"),
        ("fleet_03", "sequence"),
        ("fleet_04", "sequence"),
        ("drive", "bag"),
    ]
    assert found[0].path == root  # a root with one sequence stays as given; the same sequence again counts once
    assert found[2].path == fleet / "sequences" / "03"  # a root with several: one input per sequence

    with pytest.raises(BatchError, match="matches nothing"):
        expand_inputs([str(tmp_path / "none*")])
    with pytest.raises(BatchError, match="does not exist"):
        expand_inputs([str(tmp_path / "missing")])
    with pytest.raises(BatchError, match="no input given"):
        expand_inputs([])
    other = tmp_path / "elsewhere" / "drive"
    other.mkdir(parents=True)
    (other / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(BatchError, match="would both write OUT_DIR/drive"):
        expand_inputs([str(bag), str(other)])


def _imports(module: Path) -> set[str]:
    names = set()
    for node in ast.walk(ast.parse(module.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names.add(node.module)
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def test_the_front_ends_do_not_import_each_other_back() -> None:
    """pipeline picks the front end; label_bag and odometry.run import neither it nor each other."""
    label_bag = _imports(PACKAGE / "bags" / "label_bag.py")
    odometry = _imports(PACKAGE / "odometry" / "run.py")
    reports = _imports(PACKAGE / "reports.py")
    for imported in (label_bag, odometry, reports):
        assert "selfcontra_ros.pipeline" not in imported
    assert "selfcontra_ros.bags.label_bag" not in odometry
    assert "selfcontra_ros.odometry.run" not in label_bag
    assert not {"selfcontra_ros.bags.label_bag", "selfcontra_ros.odometry.run"} & reports
    assert {"selfcontra_ros.bags.label_bag", "selfcontra_ros.odometry.run"} <= _imports(PACKAGE / "pipeline.py")
    engine = _imports(PACKAGE / "batch" / "engine.py")
    assert "ray" in engine  # imported inside a function, after the local cluster's environment is set
    module_level = {
        n.module if isinstance(n, ast.ImportFrom) else n.names[0].name
        for n in ast.parse((PACKAGE / "batch" / "engine.py").read_text()).body
        if isinstance(n, (ast.Import, ast.ImportFrom))
    }
    assert "ray" not in module_level
