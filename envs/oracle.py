"""Oracle codes: the codes a perfect DORP encoder could learn, read off the true frame.

:class:`OracleCodeEncoder` has the interface of :class:`~dorp_rl.modules.DiscreteCodeEncoder`
(``forward(pixels) -> (code, code_probs)``, ``encode``, ``code_sizes``) but computes the
codes from the objects' colours instead of learning them: one one-hot per object of a
rearrangement env holding which ``cell_size x cell_size`` region its top-left corner lies
in, or, in the key rooms, the agent's region plus a key bit. It separates what a planner
does from how good the learned codes are (tests, ablations, debugging a planner).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from dorp_rl.envs.grid_base import GRID_SIZE, GridWorldEnv
from dorp_rl.envs.spec import env_identity
from dorp_rl.frames import frames_to_uint8
from dorp_rl.validation import check_int


class OracleCodeEncoder(nn.Module):
    """Codes from the true positions of the objects, found by their colours.

    Rearrangement: one one-hot per block, ``code = (row // s) * ceil(16 / s) + col // s``
    for the block's top-left cell and ``s = cell_size``. Key rooms: the agent's region the
    same way, and a 2-way key bit (1 once the key is taken). Frames must be renders of
    ``env``'s kind: uint8, or floats in ``[0, 1]`` (read as ``round(255 x)``).

    Args:
        env: the environment whose frames are encoded (its colours and object count).
        cell_size: side of the square regions, in cells.

    Examples:
        >>> import torch
        >>> from dorp_rl.envs import ObjectRearrangementEnv
        >>> from dorp_rl.envs import OracleCodeEncoder
        >>> env = ObjectRearrangementEnv(num_objects=2, seed=0)
        >>> oracle = OracleCodeEncoder(env, cell_size=4)
        >>> state = torch.tensor([[0, 0], [5, 9]])
        >>> oracle.encode(env.render_state(state)).tolist(), oracle.code_sizes
        ([0, 6], (16, 16))
    """

    def __init__(self, env: GridWorldEnv, cell_size: int = 4) -> None:
        super().__init__()
        self.cell_size = check_int("cell_size", cell_size, low=1)
        side = math.ceil(GRID_SIZE / self.cell_size)
        layout = getattr(env, "oracle_layout", None)
        if not callable(layout):
            raise ValueError(
                f"env must declare oracle_layout() (the colours the oracle finds, and whether "
                f"the last one is a key bit), as an ObjectRearrangementEnv or a KeyRoomEnv "
                f"does; got {type(env).__name__}."
            )
        colours, self.has_key_bit = layout()
        positions = len(colours) - (1 if self.has_key_bit else 0)
        self.code_sizes = (side * side,) * positions + ((2,) if self.has_key_bit else ())
        self.side = side
        self.num_onehots = len(self.code_sizes)
        self.max_codes = max(self.code_sizes)
        #: the env whose frames it reads (checked against play data and graphs)
        self.env_config = env_identity(env)
        self.register_buffer("colours", colours)

    def forward(self, pixels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        frames = frames_to_uint8(pixels, shape=(3, GRID_SIZE, GRID_SIZE)).to(torch.int64)
        colours = self.colours.to(frames.device)
        masks = (frames.unsqueeze(-4) == colours.view(-1, 3, 1, 1)).all(-3)  # [*B, K, H, W]
        rows = masks.any(-1).to(torch.int64).argmax(-1)  # first row holding the colour
        cols = masks.any(-2).to(torch.int64).argmax(-1)
        region = (rows // self.cell_size) * self.side + cols // self.cell_size
        if self.has_key_bit:
            key_taken = ~masks[..., 1, :, :].flatten(-2).any(-1)
            code = torch.stack([region[..., 0], key_taken.to(torch.int64)], -1)
        else:
            code = region
        probs = torch.nn.functional.one_hot(code, self.max_codes).to(torch.float32)
        return code, probs

    @torch.no_grad()
    def encode(self, pixels: torch.Tensor, chunk_size: int = 4096) -> torch.Tensor:
        """Codes int64 ``[*B, C]`` of frames ``[*B, 3, 16, 16]``."""
        flat = pixels.reshape(-1, *pixels.shape[-3:])
        codes = [self(chunk)[0] for chunk in flat.split(chunk_size)]
        return torch.cat(codes).reshape(*pixels.shape[:-3], self.num_onehots)

    def extra_repr(self) -> str:
        return f"code_sizes={self.code_sizes}, cell_size={self.cell_size}"
