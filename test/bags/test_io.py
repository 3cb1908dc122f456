"""bags.io: exact round trips through rosbags and the independent `mcap` reader, and the
one-line errors for missing, non-bag, truncated and existing paths."""

from __future__ import annotations

import contextlib
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml
from rosbags.interfaces import QosDurability, QosReliability

from bags.errors import (
    BagError,
    BagExistsError,
    BagNotFoundError,
    BagTopicError,
    CorruptBagError,
    NotABagError,
)
from bags.io import BagReader, BagWriter, RawMessage, typestore, write_text_atomic

TS = typestore()
Time = TS.types["builtin_interfaces/msg/Time"]
Header = TS.types["std_msgs/msg/Header"]
Image = TS.types["sensor_msgs/msg/Image"]
Imu = TS.types["sensor_msgs/msg/Imu"]
Quaternion = TS.types["geometry_msgs/msg/Quaternion"]
Vector3 = TS.types["geometry_msgs/msg/Vector3"]
Transform = TS.types["geometry_msgs/msg/Transform"]
TransformStamped = TS.types["geometry_msgs/msg/TransformStamped"]
TFMessage = TS.types["tf2_msgs/msg/TFMessage"]
String = TS.types["std_msgs/msg/String"]


def _header(ns: int, frame: str) -> object:
    return Header(stamp=Time(sec=ns // 10**9, nanosec=ns % 10**9), frame_id=frame)


def _imu(ns: int, k: int) -> object:
    cov = np.zeros(9, dtype=np.float64)
    return Imu(
        header=_header(ns, "imu_link"),
        orientation=Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
        orientation_covariance=cov - 1.0,
        angular_velocity=Vector3(x=0.1 * k, y=-0.2, z=1e-7 * k),
        angular_velocity_covariance=cov,
        linear_acceleration=Vector3(x=0.0, y=0.5, z=9.81),
        linear_acceleration_covariance=cov,
    )


def _image(ns: int, k: int) -> object:
    rng = np.random.default_rng(k)
    # 640x480 so that the sample bag spans several 1 MiB MCAP chunks
    data = rng.integers(0, 256, size=480 * 640, dtype=np.uint8)
    return Image(
        header=_header(ns, "camera_optical_frame"),
        height=480,
        width=640,
        encoding="mono8",
        is_bigendian=0,
        step=640,
        data=data,
    )


def _tf(ns: int) -> object:
    tr = Transform(
        translation=Vector3(x=0.1, y=0.0, z=0.0),
        rotation=Quaternion(x=-0.5, y=0.5, z=-0.5, w=0.5),
    )
    return TFMessage(
        transforms=[
            TransformStamped(
                header=_header(ns, "imu_link"), child_frame_id="camera_optical_frame", transform=tr
            )
        ]
    )


T0 = 1_700_000_000_000_000_000


def _write_sample(path: Path, **kw: object) -> list[RawMessage]:
    """A small bag with every QoS kind; returns what was written in log-time order."""
    written: list[RawMessage] = []
    with BagWriter(path, **kw) as bag:  # type: ignore[arg-type]
        bag.add_topic("/tf_static", "tf2_msgs/msg/TFMessage", qos="latched")
        bag.add_topic("/imu/data", "sensor_msgs/msg/Imu", qos="sensor")
        bag.add_topic("/camera/image_raw", "sensor_msgs/msg/Image", qos="sensor")
        bag.add_topic("/note", "std_msgs/msg/String", qos="reliable")
        bag.set_custom_data("scenario", "unit-test")

        def put(topic: str, msgtype: str, ns: int, msg: object) -> None:
            bag.write(topic, ns, msg)
            data = bytes(TS.serialize_cdr(msg, msgtype))
            written.append(RawMessage(topic, msgtype, ns, data))

        put("/tf_static", "tf2_msgs/msg/TFMessage", T0, _tf(T0))
        for k in range(40):
            ns = T0 + k * 5_000_000
            put("/imu/data", "sensor_msgs/msg/Imu", ns, _imu(ns, k))
            if k % 7 == 0:
                put("/camera/image_raw", "sensor_msgs/msg/Image", ns + 1, _image(ns + 1, k))
        raw = bytes(TS.serialize_cdr(String(data="raw bytes ünïcode"), "std_msgs/msg/String"))
        bag.write_raw("/note", T0 + 10**9, raw)
        written.append(RawMessage("/note", "std_msgs/msg/String", T0 + 10**9, raw))
    return written


def test_round_trip_rosbags_exact(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    written = _write_sample(out)
    assert sorted(p.name for p in out.iterdir()) == ["bag.mcap", "metadata.yaml"]
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # no temporary left behind
    with BagReader(out) as bag:
        got = list(bag.messages())
        assert got == written  # topic, type, log time and CDR bytes, in log-time order
        assert bag.start_ns == T0 and bag.end_ns == T0 + 10**9
        assert bag.message_count == len(written)
        assert bag.topics["/imu/data"].count == 40
        assert bag.topics["/camera/image_raw"].msgtype == "sensor_msgs/msg/Image"
        assert bag.topics["/tf_static"].qos_kind == "latched"
        assert bag.topics["/imu/data"].qos_kind == "sensor"
        assert bag.topics["/note"].qos_kind == "reliable"
        (tf_qos,) = bag.topics["/tf_static"].offered_qos
        assert tf_qos.durability == QosDurability.TRANSIENT_LOCAL
        assert tf_qos.reliability == QosReliability.RELIABLE
        imu = bag.deserialize(got[1])
        assert imu.angular_velocity.x == 0.0 and imu.linear_acceleration.z == 9.81
        img = bag.deserialize(next(m for m in got if m.topic == "/camera/image_raw"))
        np.testing.assert_array_equal(img.data, _image(0, 0).data)
        only = list(bag.messages(["/note", "/tf_static"]))
        assert [m.topic for m in only] == ["/tf_static", "/note"]
        assert bag.deserialize(only[1]).data == "raw bytes ünïcode"
        assert bag.custom_data == {"scenario": "unit-test"}
    # the bare .mcap file reads the same, custom data from rosbag2's metadata record in it
    with BagReader(out / "bag.mcap") as bag:
        assert list(bag.messages()) == written
        assert bag.custom_data == {"scenario": "unit-test"}


def test_round_trip_mcap_reader_and_metadata(tmp_path: Path, mcap_read) -> None:
    out = tmp_path / "bag"
    written = _write_sample(out)
    msgs = mcap_read(out)
    assert [(m.topic, m.log_time_ns, m.data) for m in msgs] == [
        (w.topic, w.log_time_ns, w.data) for w in written
    ]
    assert {m.schema_name for m in msgs if m.topic == "/imu/data"} == {"sensor_msgs/msg/Imu"}
    first_imu = next(m.decoded for m in msgs if m.topic == "/imu/data")
    assert first_imu.header.frame_id == "imu_link"
    assert first_imu.linear_acceleration.z == 9.81
    tf = next(m for m in msgs if m.topic == "/tf_static")
    assert tf.decoded.transforms[0].transform.rotation.w == 0.5
    assert yaml.safe_load(tf.qos_yaml)[0]["durability"] == 1  # transient local
    img = next(m.decoded for m in msgs if m.topic == "/camera/image_raw")
    assert bytes(img.data) == bytes(_image(0, 0).data)

    meta = yaml.safe_load((out / "metadata.yaml").read_text())["rosbag2_bagfile_information"]
    assert meta["version"] == 8
    assert meta["storage_identifier"] == "mcap"
    assert meta["relative_file_paths"] == ["bag.mcap"]
    assert meta["message_count"] == len(written)
    assert meta["custom_data"] == {"scenario": "unit-test"}
    topics = {t["topic_metadata"]["name"]: t for t in meta["topics_with_message_count"]}
    tf_qos = yaml.safe_load(topics["/tf_static"]["topic_metadata"]["offered_qos_profiles"])
    assert tf_qos[0]["durability"] == 1 and tf_qos[0]["reliability"] == 1
    imu_qos = yaml.safe_load(topics["/imu/data"]["topic_metadata"]["offered_qos_profiles"])
    assert imu_qos[0]["reliability"] == 2  # best effort
    assert topics["/imu/data"]["message_count"] == 40


def test_truncated_file_is_one_line_error_and_recoverable(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    written = _write_sample(out)
    mcap = out / "bag.mcap"
    data = mcap.read_bytes()
    mcap.write_bytes(data[: len(data) * 2 // 3])
    with pytest.raises(CorruptBagError) as info:
        with BagReader(out):
            pass
    text = str(info.value)
    assert "\n" not in text and str(out) in text and "truncated or corrupt" in text
    # a bare truncated .mcap too
    with pytest.raises(CorruptBagError):
        with BagReader(mcap):
            pass
    with BagReader(out, recover=True) as bag:
        got = list(bag.messages())
        assert bag.damage is not None and "\n" not in bag.damage
    # what was recovered is an exact prefix of what was written (none of it invented)
    assert 0 < len(got) < len(written)
    assert got == written[: len(got)]
    # an unfinished recording: no metadata.yaml, truncated .mcap
    (out / "metadata.yaml").unlink()
    with pytest.raises(NotABagError):
        BagReader(out)
    with BagReader(out, recover=True) as bag:
        assert list(bag.messages()) == got
        assert bag.topics["/imu/data"].qos_kind == "sensor"
        assert bag.topics["/tf_static"].qos_kind == "latched"


def test_a_byte_changed_inside_a_message_is_detected(tmp_path: Path) -> None:
    """BagWriter fills in the MCAP chunk checksums (rosbags writes 0, "not computed"), so a
    flipped bit inside an image's pixels, which leaves the structure intact, is reported
    instead of being read as a slightly different image; recover mode keeps what is before
    the damaged chunk, exactly as written."""
    out = tmp_path / "bag"
    written = _write_sample(out)
    mcap = out / "bag.mcap"
    data = bytearray(mcap.read_bytes())
    images = [m for m in written if m.topic == "/camera/image_raw"]
    victim = images[-1].data
    at = data.find(victim[-4096:])  # inside the pixels of the last image (last chunk)
    assert at > 0 and data.find(victim[-4096:], at + 1) < 0
    data[at + 100] ^= 0x10
    mcap.write_bytes(data)
    with BagReader(out) as bag:  # the summary is intact
        assert bag.topics["/camera/image_raw"].count == len(images)
        with pytest.raises(CorruptBagError) as info:
            list(bag.messages())
    text = str(info.value)
    assert "\n" not in text and str(out) in text and "checksum" in text
    with BagReader(out, recover=True) as bag:
        got = list(bag.messages())
        assert bag.damage is not None and "checksum" in bag.damage
    assert 0 < len(got) < len(written)
    assert got == written[: len(got)]
    assert all(m.data != victim for m in got)


def test_recover_reads_an_intact_mcap_without_metadata(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    written = _write_sample(out)
    (out / "metadata.yaml").unlink()
    with BagReader(out, recover=True) as bag:
        assert bag.damage is None  # indexed read of the single .mcap
        assert list(bag.messages()) == written


def test_not_a_bag_and_missing(tmp_path: Path) -> None:
    with pytest.raises(BagNotFoundError, match=r"bag not found: .*nope"):
        BagReader(tmp_path / "nope")
    (tmp_path / "dir").mkdir()
    (tmp_path / "dir" / "x.txt").write_text("hello")
    with pytest.raises(NotABagError, match=r"without metadata\.yaml$"):
        BagReader(tmp_path / "dir")
    # a dataset folder: the error names the tool that converts it
    (tmp_path / "euroc" / "mav0" / "cam0").mkdir(parents=True)
    kitti = tmp_path / "kitti"
    kitti.mkdir()
    (kitti / "times.txt").write_text("0.0\n")
    (kitti / "calib.txt").write_text("P0: 1 0 0 0 0 1 0 0 0 0 1 0\n")
    for folder, kind in (
        (tmp_path / "euroc", "an ASL"),
        (tmp_path / "euroc" / "mav0", "an ASL"),
        (kitti, "a KITTI"),
    ):
        with pytest.raises(NotABagError) as err:
            BagReader(folder)
        assert f"({kind}" in str(err.value)
        assert str(err.value).endswith(f"convert it first with owl_import {folder} OUT_BAG)")
    (tmp_path / "file.mcap").write_bytes(b"not an mcap at all")
    with pytest.raises(NotABagError, match=r"file\.mcap"):
        BagReader(tmp_path / "file.mcap")
    bad_meta = tmp_path / "badmeta"
    bad_meta.mkdir()
    (bad_meta / "metadata.yaml").write_text("rosbag2_bagfile_information: [1, 2\n")
    with pytest.raises(CorruptBagError, match="badmeta"):
        with BagReader(bad_meta):
            pass


def test_writer_refuses_existing_and_overwrites_bags_only(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    _write_sample(out)
    with pytest.raises(BagExistsError, match="exists"):
        BagWriter(out)
    second = _write_sample(out, overwrite=True)
    with BagReader(out) as bag:
        assert list(bag.messages()) == second
    other = tmp_path / "notabag"
    other.mkdir()
    (other / "precious.txt").write_text("keep me")
    with pytest.raises(BagExistsError, match="not a rosbag2 directory"):
        BagWriter(other, overwrite=True)
    assert (other / "precious.txt").read_text() == "keep me"
    with pytest.raises(BagError, match="does not exist"):
        BagWriter(tmp_path / "missing_parent" / "bag")


def test_writer_removes_half_written_output(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    with pytest.raises(RuntimeError, match="boom"):
        with BagWriter(out) as bag:
            bag.add_topic("/note", "std_msgs/msg/String")
            bag.write("/note", 5, String(data="x"))
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []
    # with overwrite, a failure leaves the previous bag untouched
    first = _write_sample(out)
    with pytest.raises(RuntimeError):
        with BagWriter(out, overwrite=True) as bag:
            bag.add_topic("/note", "std_msgs/msg/String")
            raise RuntimeError("boom")
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]
    with BagReader(out) as reader:
        assert list(reader.messages()) == first


def test_topic_errors(tmp_path: Path) -> None:
    out = tmp_path / "bag"
    with pytest.raises(BagTopicError, match="/other"):
        with BagWriter(out) as bag:
            bag.add_topic("/note", "std_msgs/msg/String")
            bag.write("/other", 1, String(data="x"))
    assert not out.exists()
    with pytest.raises(BagTopicError, match="no_pkg/msg/Nope"):
        with BagWriter(out) as bag:
            bag.add_topic("/x", "no_pkg/msg/Nope")
    with pytest.raises(BagTopicError, match="qos"):
        with BagWriter(out) as bag:
            bag.add_topic("/x", "std_msgs/msg/String", qos="fast")
    with pytest.raises(BagTopicError, match="twice"):
        with BagWriter(out) as bag:
            bag.add_topic("/x", "std_msgs/msg/String")
            bag.add_topic("/x", "std_msgs/msg/String")
    _write_sample(out)
    with BagReader(out) as bag:
        with pytest.raises(BagTopicError, match="/nope not in bag"):
            list(bag.messages(["/nope"]))
    shutil.rmtree(out)


def test_check_output_refuses_the_input_inside_it_or_containing_it(tmp_path: Path) -> None:
    from bags.errors import OutputOverlapError
    from bags.io import check_output

    bag = tmp_path / "in_bag"
    bag.mkdir()
    (bag / "in_bag_0.mcap").write_bytes(b"x")
    for out, how in ((bag, "is"), (bag / "sub", "is inside"), (tmp_path, "contains")):
        with pytest.raises(OutputOverlapError, match=f"the output {how} the input"):
            check_output(out, [bag], overwrite=True)
    with pytest.raises(OutputOverlapError, match="is the input"):  # same path, other spelling
        check_output(tmp_path / "x" / ".." / "in_bag", [bag], overwrite=True)
    with pytest.raises(BagExistsError, match=r"exists \(add --overwrite to replace it\)"):
        check_output(bag, [], overwrite=False)
    check_output(tmp_path / "new", [bag])  # unrelated and absent: fine
    # BagWriter applies it even with overwrite (it would otherwise rmtree the input)
    mcap = tmp_path / "out" / "rec.mcap"
    mcap.parent.mkdir()
    mcap.write_bytes(b"x")
    with pytest.raises(OutputOverlapError, match="contains the input"):
        BagWriter(mcap.parent, overwrite=True, inputs=[mcap])
    assert mcap.read_bytes() == b"x"


def test_chunks_are_zstd_compressed_with_checksums(tmp_path: Path, mcap_read) -> None:
    from mcap.records import Chunk
    from mcap.stream_reader import StreamReader

    def write(path: Path, compress: bool) -> Path:
        with BagWriter(path, compress=compress) as bag:
            bag.add_topic("/imu/data", "sensor_msgs/msg/Imu", "sensor")
            for i in range(2000):
                header = Header(stamp=Time(sec=i, nanosec=0), frame_id="imu")
                msg = Imu(
                    header=header, orientation=Quaternion(x=0, y=0, z=0, w=1),
                    orientation_covariance=np.zeros(9), angular_velocity=Vector3(x=i, y=0, z=0),
                    angular_velocity_covariance=np.zeros(9),
                    linear_acceleration=Vector3(x=0, y=0, z=9.81),
                    linear_acceleration_covariance=np.zeros(9),
                )  # fmt: skip
                bag.write("/imu/data", i * 1_000_000, msg)
        return next(path.glob("*.mcap"))

    small, plain = write(tmp_path / "z", True), write(tmp_path / "p", False)
    with small.open("rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert chunks and {c.compression for c in chunks} == {"zstd"}
    assert small.stat().st_size < plain.stat().st_size / 2
    # both read back the same, CRCs present and verified by the independent reader
    assert [m.data for m in mcap_read(small)] == [m.data for m in mcap_read(plain)]
    with BagReader(tmp_path / "z") as bag:
        assert bag.topics["/imu/data"].count == 2000
    (tmp_path / "again").mkdir()  # the same name (it is in the metadata), same bytes
    assert write(tmp_path / "again" / "z", True).read_bytes() == small.read_bytes()


def test_output_inside_the_bag_of_an_mcap_input_is_refused(tmp_path: Path) -> None:
    from bags.errors import OutputOverlapError
    from bags.io import check_output

    bag = tmp_path / "b1"
    _write_sample(bag)
    mcap = next(bag.glob("*.mcap"))
    for out in (bag / "res", bag / "sub" / ".." / "res2"):  # inside the bag of the file
        with pytest.raises(OutputOverlapError, match=f"is inside the input bag {bag} \\(of "):
            check_output(out, [mcap], overwrite=True)
        with pytest.raises(OutputOverlapError, match="input bag"):
            BagWriter(out, overwrite=True, inputs=[mcap])
    assert sorted(p.name for p in bag.iterdir()) == ["b1.mcap", "metadata.yaml"]
    BagWriter(tmp_path / "res", inputs=[mcap])  # next to the bag: fine
    # a bare .mcap in an ordinary folder: an output next to it is fine
    loose = tmp_path / "loose"
    loose.mkdir()
    shutil.copy(mcap, loose / "rec.mcap")
    (loose / "notes.txt").write_text("x")
    check_output(loose / "res", [loose / "rec.mcap"])


@contextlib.contextmanager
def _unwritable(folder: Path) -> Iterator[None]:
    """``folder`` made unwritable for real: its mode for a normal user; root ignores the
    mode, so then the immutable attribute (chattr +i, on ext4/xfs/btrfs), or skip."""
    if os.geteuid() != 0:
        folder.chmod(0o555)
        try:
            yield
        finally:
            folder.chmod(0o755)
        return
    chattr = shutil.which("chattr")
    if chattr is None or subprocess.run([chattr, "+i", str(folder)], check=False).returncode:
        pytest.skip("running as root and chattr +i is not possible here")
    try:
        yield
    finally:
        subprocess.run([chattr, "-i", str(folder)], check=True)


def test_unwritable_output_directory_is_a_one_line_bag_error(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    with _unwritable(folder):
        writer = BagWriter(folder / "out")
        with pytest.raises(BagError, match=f"^cannot write bag {folder / 'out'}: [A-Z]") as err:
            with writer:
                pass
        assert "\n" not in str(err.value) and not isinstance(err.value, OSError)
        assert list(folder.iterdir()) == []


#: A bag of 100 kB notes written in a child process (see the limited_run fixture):
#: argv = out, number of notes, "keep" (keep_partial) or "drop".
_NOTES_WRITER = """
import sys
from bags.errors import BagError
from bags.io import BagWriter, typestore
String = typestore().types["std_msgs/msg/String"]
out, count, keep = sys.argv[1], int(sys.argv[2]), sys.argv[3] == "keep"
try:
    with BagWriter(out, overwrite=True, compress=False, keep_partial=keep) as bag:
        bag.add_topic("/note", "std_msgs/msg/String")
        for i in range(count):
            bag.write("/note", 1000 + i, String(data=f"{i:06d}" + "x" * 99_994))
except BagError as err:
    print(err)
    sys.exit(1)
"""


def _note_texts(path: Path, recover: bool = False) -> list[str]:
    with BagReader(path, recover=recover) as bag:
        return [bag.deserialize(raw).data[:6] for raw in bag.messages()]


def _chunk_ends(mcap: Path) -> list[int]:
    """Where each chunk's records (the chunk and its message indexes) end in ``mcap``."""
    data = mcap.read_bytes()
    ends: list[int] = []
    pos, in_chunk = 8, False
    while pos + 9 <= len(data):
        op = data[pos]
        if in_chunk and op != 0x07:  # not a message index: the previous chunk ends here
            ends.append(pos)
        in_chunk = op == 0x06 or (in_chunk and op == 0x07)
        if op == 0x0F:  # DataEnd
            break
        pos += 9 + int.from_bytes(data[pos + 1 : pos + 9], "little")
    return ends


@pytest.mark.parametrize("finishable", [True, False])
def test_write_error_keep_partial_keeps_what_was_written(
    tmp_path: Path, limited_run, finishable: bool
) -> None:
    reference = tmp_path / "reference"
    assert limited_run(["-c", _NOTES_WRITER, str(reference), "30", "keep"], 2**30).returncode == 0
    first_end = _chunk_ends(next(reference.glob("*.mcap")))[0]
    # files cannot grow past the first chunk + room: the second chunk's write fails (EFBIG)
    # and, with 40 bytes of room, closing the bag after the first chunk fails too
    out = tmp_path / "rec"
    room = 65536 if finishable else 40
    res = limited_run(["-c", _NOTES_WRITER, str(out), "30", "keep"], first_end + room)
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    (line,) = res.stdout.splitlines()
    assert line.startswith(f"cannot write bag {out}: File too large; ")
    kept = _note_texts(out, recover=True)  # the first chunk's notes, in order
    assert kept == [f"{i:06d}" for i in range(len(kept))] and 1 <= len(kept) < 30
    if finishable:
        assert line.endswith(f"closed it with the {len(kept)} messages written before")
        assert (out / "metadata.yaml").is_file()
        assert _note_texts(out) == kept  # a finished bag: no recovery needed
    else:
        unfinished = f"the {len(kept)} messages written before it are in the unfinished bag"
        assert f"{unfinished} {out} " in line
        assert not (out / "metadata.yaml").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["rec", "reference"]


def test_write_error_deletes_only_the_temporary_output(tmp_path: Path, limited_run) -> None:
    out = tmp_path / "bag"
    previous = _write_sample(out)
    res = limited_run(["-c", _NOTES_WRITER, str(out), "30", "drop"], 300_000)
    assert res.returncode == 1 and "Traceback" not in res.stderr, res.stderr
    assert res.stdout.strip() == f"cannot write bag {out}: File too large"
    assert [p.name for p in tmp_path.iterdir()] == ["bag"]  # no temporary left
    with BagReader(out) as bag:  # the bag it would have replaced is untouched
        assert list(bag.messages()) == previous


def test_write_text_atomic_replaces_whole_or_not_at_all(tmp_path: Path) -> None:
    out = tmp_path / "calib.yaml"
    out.write_text("old\n")
    write_text_atomic(out, "new\n")
    assert out.read_text() == "new\n"
    # a write that fails half way (a character UTF-8 cannot encode) keeps the old file
    with pytest.raises(UnicodeEncodeError):
        write_text_atomic(out, "partial " + "\ud800")
    assert out.read_text() == "new\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["calib.yaml"]  # no temporary left
