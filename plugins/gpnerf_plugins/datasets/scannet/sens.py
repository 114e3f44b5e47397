"""Streaming reader of ScanNet's ``.sens`` RGB-D files.

Written from the format as ScanNet publishes it: ``SensReader/src/sensorData.h`` (``SensorData::writeHeaderToFile``,
``SensorData::loadFromFile``, ``CalibrationData::saveToFile``, ``RGBDFrame::saveToFile``) and the Python exporter
``SensReader/python/SensorData.py`` in the ScanNet/ScanNet repository. Little-endian (the files come from x86
machines), no padding between fields::

    header
      uint32       version                     4 (M_SENSOR_DATA_VERSION; 0-2 were the older .sensor files)
      uint64 n     sensor name length, then n bytes
      float32[16]  colour intrinsic  }  CalibrationData of the colour camera: intrinsic then extrinsic
      float32[16]  colour extrinsic  }
      float32[16]  depth intrinsic   }  CalibrationData of the depth camera (its extrinsic maps depth to colour)
      float32[16]  depth extrinsic   }
      int32        colour compression          -1 unknown, 0 raw, 1 png, 2 jpeg (ScanNet: jpeg)
      int32        depth compression           -1 unknown, 0 raw_ushort, 1 zlib_ushort, 2 occi_ushort (ScanNet: zlib)
      uint32 x 4   colour width, colour height, depth width, depth height
      float32      depth shift                 depth units per metre (1000: millimetres)
      uint64       number of RGB-D frames
    per frame
      float32[16]  camera-to-world             all -inf where tracking was lost (RGBDFrame's default)
      uint64 x 2   colour and depth timestamps (microseconds)
      uint64 x 2   colour and depth byte counts
      bytes        colour data, then depth data
    then uint64 number of IMU frames and their records (not read here)

Matrices are ``mat4f`` stored row-major (``_m00, _m01, ...``). A zlib_ushort depth frame is one zlib stream of
``depth_width * depth_height`` uint16 values, row by row.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO, Iterator

import numpy as np

from gpnerf_core import DataError

SENS_VERSION = 4
COLOR_COMPRESSION = {-1: "unknown", 0: "raw", 1: "png", 2: "jpeg"}
DEPTH_COMPRESSION = {-1: "unknown", 0: "raw_ushort", 1: "zlib_ushort", 2: "occi_ushort"}
_FRAME_FIXED = struct.Struct("<16f4Q")  # camera_to_world, timestamps, byte counts: 96 bytes


@dataclass(frozen=True)
class SensHeader:
    """The header of a ``.sens`` file.

    Attributes:
        version: format version (4).
        sensor_name: e.g. ``StructureSensor``.
        intrinsic_color, extrinsic_color, intrinsic_depth, extrinsic_depth: ``[4, 4]`` float32.
        color_compression, depth_compression: names from ``COLOR_COMPRESSION`` / ``DEPTH_COMPRESSION``.
        color_width, color_height, depth_width, depth_height: image sizes, pixels.
        depth_shift: stored depth units per metre.
        num_frames: RGB-D frames that follow the header.
    """

    version: int
    sensor_name: str
    intrinsic_color: np.ndarray
    extrinsic_color: np.ndarray
    intrinsic_depth: np.ndarray
    extrinsic_depth: np.ndarray
    color_compression: str
    depth_compression: str
    color_width: int
    color_height: int
    depth_width: int
    depth_height: int
    depth_shift: float
    num_frames: int


@dataclass(frozen=True)
class SensFrame:
    """One RGB-D frame as stored.

    Attributes:
        index: position in the stream (ScanNet's exported frame name).
        camera_to_world: ``[4, 4]`` float32, OpenCV camera, metres; non-finite when tracking was lost.
        timestamp_color, timestamp_depth: microseconds.
        color: compressed colour bytes (a JPEG file for ScanNet), or b"" when skipped.
        depth: compressed depth bytes, or b"" when skipped.
    """

    index: int
    camera_to_world: np.ndarray
    timestamp_color: int
    timestamp_depth: int
    color: bytes
    depth: bytes


class SensReader:
    """Reads the header on construction and streams frames one at a time (the file is never loaded whole).

    Use as a context manager, or call ``close``. Every malformed or truncated field raises a one-line
    ``DataError`` naming the file, the field and the frame.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise DataError(f"{self.path}: missing; expected a ScanNet .sens RGB-D stream")
        self._size = self.path.stat().st_size
        self._handle: BinaryIO = self.path.open("rb")
        try:
            self.header = self._read_header()
        except BaseException:
            self._handle.close()
            raise
        self._frames_offset = self._handle.tell()

    def __enter__(self) -> "SensReader":
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        self._handle.close()

    def _read(self, count: int, what: str, frame: int | None = None) -> bytes:
        where = f" of frame {frame}" if frame is not None else ""
        remaining = self._size - self._handle.tell()
        if count > remaining:
            raise DataError(
                f"{self.path}: truncated in the {what}{where}; expected {count} bytes, found {max(remaining, 0)}"
            )
        return self._handle.read(count)

    def _unpack(self, fmt: str, what: str, frame: int | None = None) -> tuple:
        layout = struct.Struct("<" + fmt)
        return layout.unpack(self._read(layout.size, what, frame))

    def _matrix(self, what: str) -> np.ndarray:
        return np.asarray(self._unpack("16f", what), dtype=np.float32).reshape(4, 4)

    def _read_header(self) -> SensHeader:
        (version,) = self._unpack("I", "version")
        if version != SENS_VERSION:
            raise DataError(
                f"{self.path}: .sens version {version}; expected {SENS_VERSION} (ScanNet's SensorData format)"
            )
        (name_length,) = self._unpack("Q", "sensor name length")
        name = self._read(name_length, "sensor name").decode("utf-8", errors="replace")
        names = ("colour intrinsic", "colour extrinsic", "depth intrinsic", "depth extrinsic")
        matrices = [self._matrix(what) for what in names]
        color_type, depth_type = self._unpack("ii", "compression types")
        if color_type not in COLOR_COMPRESSION or depth_type not in DEPTH_COMPRESSION:
            raise DataError(
                f"{self.path}: compression types colour={color_type}, depth={depth_type}; expected colour in "
                f"{sorted(COLOR_COMPRESSION)} and depth in {sorted(DEPTH_COMPRESSION)}"
            )
        color_width, color_height, depth_width, depth_height = self._unpack("4I", "image sizes")
        (depth_shift,) = self._unpack("f", "depth shift")
        (num_frames,) = self._unpack("Q", "frame count")
        if min(color_width, color_height, depth_width, depth_height) < 1:
            raise DataError(
                f"{self.path}: image sizes colour {color_width}x{color_height}, depth {depth_width}x{depth_height}; "
                "expected positive sizes"
            )
        return SensHeader(
            version, name, *matrices, COLOR_COMPRESSION[color_type], DEPTH_COMPRESSION[depth_type],
            color_width, color_height, depth_width, depth_height, float(depth_shift), int(num_frames),
        )  # fmt: skip

    def frames(self, every: int = 1) -> Iterator[SensFrame]:
        """Frames ``0, every, 2 every, ...`` in stream order; the image bytes of the others are skipped, not read.

        One frame is held in memory at a time. The reader has one file position: finish (or drop) one iteration
        before starting another.

        Raises:
            DataError: the stream ends inside a frame (the message names the frame and field).
        """
        if every < 1:
            raise DataError(f"frame step {every}; expected 1 or more")
        self._handle.seek(self._frames_offset)
        for index in range(self.header.num_frames):
            values = _FRAME_FIXED.unpack(self._read(_FRAME_FIXED.size, "pose, timestamps and sizes", index))
            pose = np.asarray(values[:16], dtype=np.float32).reshape(4, 4)
            timestamp_color, timestamp_depth, color_size, depth_size = values[16:]
            if index % every:
                if color_size + depth_size > self._size - self._handle.tell():
                    self._read(color_size + depth_size, "colour and depth data", index)  # raises: truncated
                self._handle.seek(color_size + depth_size, 1)
                continue
            color = self._read(color_size, "colour data", index)
            depth = self._read(depth_size, "depth data", index)
            yield SensFrame(index, pose, timestamp_color, timestamp_depth, color, depth)

    def depth_image(self, frame: SensFrame) -> np.ndarray:
        """Decompress a frame's depth: ``[depth_height, depth_width]`` uint16 in units of ``1 / depth_shift`` m."""
        header = self.header
        if header.depth_compression == "zlib_ushort":
            try:
                data = zlib.decompress(frame.depth)
            except zlib.error as exc:
                raise DataError(f"{self.path}: depth of frame {frame.index} is not a zlib stream ({exc})") from None
        elif header.depth_compression == "raw_ushort":
            data = frame.depth
        else:
            raise DataError(
                f"{self.path}: depth compression {header.depth_compression}; expected zlib_ushort or raw_ushort"
            )
        expected = header.depth_width * header.depth_height * 2
        if len(data) != expected:
            raise DataError(
                f"{self.path}: depth of frame {frame.index} has {len(data)} bytes; expected {expected} "
                f"({header.depth_width}x{header.depth_height} uint16)"
            )
        return np.frombuffer(data, dtype="<u2").reshape(header.depth_height, header.depth_width)
