"""The bus's data: what a drive's frames mean and how they are read and written.

The DBC and the signal mapping (``protocol``: :func:`~canrls.can.protocol.load_dbc`, the
one reader, and :class:`~canrls.can.protocol.Protocol`; ``mapping``), one compiled codec
per message (``codec``), strict decoding (``decoder``: a value outside its range, a bad
CRC or counter is rejected and counted, never clipped), the encoder, frame blocks,
log readers and writers (``logs``, ``candump``, ``writers``), the estimator's own
parameter, status and command frames (``estimator_frames``) and E2E protection (``e2e``). It
imports only :mod:`canrls.core`; what the frames become (samples, periods, pairs) is
the processor's.
"""
