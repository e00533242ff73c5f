"""The one frame hash: 64-bit hashes of uint8 rows (:func:`row_hashes`), and the
distinct rows of a batch (:func:`distinct_rows`), with which planners, costs and the
policy deduplicate imagined frames.
"""

from __future__ import annotations

import torch

__all__ = [
    "hash_weights",
    "distinct_rows",
    "int64_columns",
    "row_hashes",
]


_HASH_WEIGHTS: dict[tuple[torch.device, int], torch.Tensor] = {}


#: int8 limbs of the hash weights, ``(weights, limbs [num_bytes, 8])`` per (device, bytes)
_HASH_LIMBS: dict[tuple[torch.device, int], tuple[torch.Tensor, torch.Tensor]] = {}


def row_hashes(rows: torch.Tensor) -> torch.Tensor:
    """A 64-bit hash ``[n]`` of each row of a uint8 ``[n, ...]`` tensor (same bytes, same hash).

    The hash is ``sum_b weight_b * byte_b`` modulo 2**64 with an odd random weight per
    byte position (:func:`hash_weights`). Odd weights make any one changed byte change
    the hash, and two different rows share a hash with probability at most about 2**-56
    (a weighted sum of byte differences, each below 2**8 in size, vanishing modulo
    2**64). A weight per 8-byte word instead would let a difference in a word's top byte
    reach only the hash's top 8 bits: frames differing there collided one time in 256.

    On the CPU the sum is one int8 matrix product (:func:`_byte_hashes`): a pass over the
    bytes, about 11 ms for 4000 rows of 3 x 76 x 76 bytes on one thread (the int64 sum
    it replaces took 0.54 s).
    """
    n = rows.shape[0]
    flat = rows.reshape(n, rows[0].numel() if n else rows.shape[1:].numel())
    weights = hash_weights(rows.device, flat.shape[1])
    if flat.dtype == torch.uint8 and flat.device.type == "cpu" and hasattr(torch, "_int_mm"):
        return _byte_hashes(flat, weights)
    out = torch.empty(n, dtype=torch.int64, device=rows.device)
    for start in range(0, n, _HASH_CHUNK):  # bounds the int64 copy of the bytes
        chunk = flat[start : start + _HASH_CHUNK].to(torch.int64)
        out[start : start + _HASH_CHUNK] = (chunk * weights).sum(-1)
    return out


#: rows hashed at once by :func:`row_hashes` off the CPU
_HASH_CHUNK = 2048


#: bytes of rows converted at once by :func:`_byte_hashes` (stays in cache)
_HASH_CHUNK_BYTES = 1 << 22


#: columns per int8 product of :func:`_byte_hashes`: its int32 sums of ``K`` products of
#: at most 2**14 in size stay below 2**31
_HASH_BLOCK = 131064


_LIMB_SHIFTS = torch.tensor([1 << (8 * k) for k in range(8)], dtype=torch.int64)


def _hash_limbs(weights: torch.Tensor) -> torch.Tensor:
    """int8 ``[D, 8]`` signed base-256 digits ``c`` of int64 weights ``[D]``:
    ``sum_k c[:, k] * 256**k == weights`` modulo 2**64."""
    key = (weights.device, weights.shape[0])
    cached = _HASH_LIMBS.get(key)
    if cached is not None and cached[0] is weights:
        return cached[1]
    limbs, carry = [], torch.zeros_like(weights)
    for k in range(8):
        value = ((weights >> (8 * k)) & 255) + carry  # 0..256
        carry = (value >= 128).to(torch.int64)
        limbs.append(value - 256 * carry)  # -128..127
    out = torch.stack(limbs, -1).to(torch.int8)
    _HASH_LIMBS[key] = (weights, out)
    return out


def _byte_hashes(flat: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`row_hashes` of CPU uint8 rows ``[n, D]``, exactly, as int8 matrix products.

    ``sum_b w_b x_b = sum_b w_b (x_b - 128) + 128 sum_b w_b``; the bytes less 128 are int8
    (``x ^ 128``), the weights int8 digits of base 256 (:func:`_hash_limbs`), so
    ``torch._int_mm`` gives the digits' sums in int32, combined modulo 2**64.
    """
    n, num_bytes = flat.shape
    out = torch.empty(n, dtype=torch.int64)
    if n == 0 or num_bytes == 0:
        return out.fill_(0)
    limbs = _hash_limbs(weights)
    offset = 128 * weights.sum()  # modulo 2**64
    rows = max(1, _HASH_CHUNK_BYTES // num_bytes)
    buffer = torch.empty(min(rows, n), num_bytes, dtype=torch.uint8)
    for start in range(0, n, rows):
        chunk = flat[start : start + rows]
        signed = torch.bitwise_xor(chunk, 128, out=buffer[: chunk.shape[0]]).view(torch.int8)
        sums = torch.zeros(chunk.shape[0], 8, dtype=torch.int64)
        for col in range(0, num_bytes, _HASH_BLOCK):
            block = slice(col, col + _HASH_BLOCK)
            sums += torch._int_mm(signed[:, block], limbs[block])
        out[start : start + rows] = (sums * _LIMB_SHIFTS).sum(-1) + offset
    return out


def hash_weights(device: torch.device, num_bytes: int) -> torch.Tensor:
    """The odd int64 weights ``[num_bytes]`` of :func:`row_hashes` for rows of that many bytes.

    The hash is linear in the bytes (modulo 2**64), which :class:`ImaginedFrames` uses to
    hash frames from their parts without drawing them.
    """
    key_id = (device, num_bytes)
    weights = _HASH_WEIGHTS.get(key_id)
    if weights is None:
        gen = torch.Generator().manual_seed(0x5EED)
        weights = torch.randint(-(2**62), 2**62, (num_bytes,), generator=gen) | 1
        weights = _HASH_WEIGHTS.setdefault(key_id, weights.to(device))
    return weights


def distinct_rows(rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """The distinct rows of a uint8 ``[n, D]`` tensor, and ``inverse`` with ``out[inverse] == rows``.

    Rows are grouped by a 64-bit hash of their bytes (one pass, no row sort); the groups
    are then checked row by row, so a hash collision never merges different rows (it
    falls back to no deduplication, ``inverse=None``). Planning repeats frames a lot
    (candidates share prefixes, blocked moves leave frames unchanged), so the models and
    encoders that run on imagined frames run on distinct ones only.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs.planning import distinct_rows
        >>> rows = torch.tensor([[1, 2], [3, 4], [1, 2]], dtype=torch.uint8)
        >>> unique, inverse = distinct_rows(rows)
        >>> unique.shape[0], bool((unique[inverse] == rows).all())
        (2, True)
    """
    n = rows.shape[0]
    if n == 0:
        return rows, torch.zeros(0, dtype=torch.long, device=rows.device)
    key = row_hashes(rows)
    unique, inverse = torch.unique(key, return_inverse=True)
    first = torch.full((unique.shape[0],), n, dtype=torch.long, device=key.device)
    first.scatter_reduce_(0, inverse, torch.arange(n, device=key.device), reduce="amin")
    representatives = rows[first]
    if not _rows_match(rows.reshape(n, -1), representatives.reshape(first.shape[0], -1), inverse):
        return rows, None
    return representatives, inverse


def _rows_match(rows: torch.Tensor, table: torch.Tensor, index: torch.Tensor) -> bool:
    """Whether ``table[index] == rows`` (``[n, D]`` each), compared as int64 words in
    chunks that stay in cache on the CPU (a uint8 comparison there is 6x slower)."""
    if rows.device.type != "cpu" or rows.dtype != torch.uint8:
        return bool((table[index] == rows).all())
    rows = rows.contiguous()
    n, num_bytes = rows.shape
    step = max(1, _HASH_CHUNK_BYTES // max(num_bytes, 1))
    step = step - step % 8 if step >= 8 else step  # chunk starts stay word-aligned
    buffer = torch.empty(min(step, n), num_bytes, dtype=torch.uint8)
    for start in range(0, n, step):
        chunk = rows[start : start + step]
        drawn = buffer[: chunk.shape[0]]
        torch.index_select(table, 0, index[start : start + step], out=drawn)
        if not torch.equal(*_words(drawn.reshape(-1), chunk.reshape(-1))):
            return False
    return True


def _words(*flats: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """1-D uint8 tensors of one length viewed as int64 words where their offsets allow."""
    if flats[0].numel() % 8 == 0 and all(f.storage_offset() % 8 == 0 for f in flats):
        try:
            return tuple(f.view(torch.int64) for f in flats)
        except RuntimeError:
            pass
    return flats


def int64_columns(columns: torch.Tensor) -> torch.Tensor:
    """int64 ``[n, k]`` of uint8 columns ``[n, 8k]`` cut from byte rows (the inverse of
    appending ``values.view(torch.uint8)``). A fresh copy is viewed, so any row width
    works: a slice of 75-byte rows, or of a lone row, cannot be viewed as int64 itself."""
    return columns.reshape(-1).clone().view(torch.int64).reshape(columns.shape[0], -1)


def _distinct_pairs(
    pixels: torch.Tensor, action: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
    """The distinct (frame, action) rows, and ``inverse`` with ``rows[inverse] == input``."""
    n = pixels.shape[0]
    action_bytes = action.reshape(n, 1).to(torch.int64).contiguous().view(torch.uint8)  # [n, 8]
    unique, inverse = distinct_rows(torch.cat([pixels.reshape(n, -1), action_bytes], -1))
    if inverse is None:
        return pixels, action, None
    frames = unique[:, :-8].reshape(-1, *pixels.shape[1:])
    actions = int64_columns(unique[:, -8:]).to(action.dtype)
    return frames, actions.reshape(-1, *action.shape[1:]), inverse
