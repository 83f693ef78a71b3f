"""The link format shared by transmitter and receiver: pure numpy, no I/O, no web.

- ``marker``: geometry of the dynamic marker, rendering, marker-frame coordinates;
- ``profiles``: the link profiles (``paper``, ``robust``, ``fast``);
- ``stream``: ``StreamEncoder`` (frame k of a message) and ``StreamDecoder`` (messages back);
- ``report``: the JSON schema the receiver sends to the server.

Their parts: ``paper_codec`` (the paper's raw RS-coded bit stream), ``frame_codec`` (one framed
data frame: header, CRC, RS, interleaving, whitening), ``framing`` (cell order, header, CRC),
``fec`` and ``rs_kernel`` (Reed-Solomon), ``fountain`` (RaptorQ blocks and their schedule).
"""
