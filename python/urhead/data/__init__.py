"""Subjects: reading and writing the VHAP / GaussianAvatars dataset layout, and the
synthetic ground-truth subjects (:mod:`urhead.data.synth`)."""

from urhead.data.layout import DatasetError, MissingFileError, decode_normals, encode_normals
from urhead.data.reader import Frame, FrameSequence, Subject, load_subject
from urhead.data.writer import SubjectWriter, opengl_c2w

__all__ = [
    "DatasetError",
    "Frame",
    "FrameSequence",
    "MissingFileError",
    "Subject",
    "SubjectWriter",
    "decode_normals",
    "encode_normals",
    "load_subject",
    "opengl_c2w",
]
