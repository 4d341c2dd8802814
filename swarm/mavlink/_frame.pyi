# The interface of swarm/mavlink/_frame.c (its methods table and PyInit__frame), for mypy.
from _typeshed import ReadableBuffer

def frame_v2(payload: ReadableBuffer, seq: int, system_id: int, component_id: int,
             message_id: int, crc_extra: int, /) -> bytes: ...
def payload_v2(data: ReadableBuffer, message_id: int, crc_extra: int, payload_size: int,
               /) -> tuple[int, int, bytes] | None: ...
