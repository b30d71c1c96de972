"""Deep Koopman model (paper section II-B, eq. latent_vehicle_dynamics; DDK, Xiao et al. 2023).

Inference only, numpy only: this module never imports torch (training lives in
``vflpcd.training.train_koopman``).

Model
-----
With the model's normalisation x_n = (x - x_mean) / x_std (x in the window frame, see
``vflpcd.core.dynamics.lifted``), the lifted state is

    Upsilon(x) = [x, rho(x)],   rho(x) = [rho_e(x_n), 1]                     (n_K,)

where the encoder rho_e: R^{n_x} -> R^{n_e}, n_e = n_K - n_x - 1, is a multilayer perceptron

    h_0 = x_n,  h_i = tanh(h_{i-1} W_i + b_i) (i < L),  rho_e = h_{L-1} W_L + b_L

(activation ``tanh`` on the hidden layers, the output layer linear; W_i (d_{i-1}, d_i),
b_i (d_i,), d_0 = n_x, d_L = n_e), evaluated in float32, the precision of its training, in the order
that ``encoder_kernel`` defines (its sums in a fixed order, its tanh a rational function within an ulp
of float32 tanh): the compiled tick's lift and numpy's give the same bits. The last lifted entry is the constant 1, the convention
of :func:`vflpcd.core.dynamics.lifted.to_physical`: it carries the affine offsets of the
normalisation, so A (n_K, n_K) and B (n_K, n_u) act on the physical [x, rho_e, 1] and the
predicted state is the first n_x entries of Upsilon_{k+1} = A Upsilon_k + B u_k (plus s_k B_s u_k for
a model whose input matrix is scheduled on a state s, ``lifted``).

The artifact (an ``.npz`` archive) is read and written by ``vflpcd.config.koopman_file``.
"""

from __future__ import annotations

from typing import Any, Mapping, Sequence

import numpy as np

from vflpcd.core.dynamics.encoder_kernel import encoder_layers
from vflpcd.core.dynamics.lifted import LiftedLinearModel, Lifter

ACTIVATION = "tanh"


def encoder_forward(x_n: np.ndarray, weights: Sequence[np.ndarray], biases: Sequence[np.ndarray]) -> np.ndarray:
    """The MLP encoder rho_e: x_n (..., n_x) -> (..., n_e) float64, by ``encoder_kernel.encoder_layers``
    (float32 weights: ``KoopmanModel`` passes float32 copies)."""
    return encoder_layers(np.asarray(x_n, dtype=np.float32), weights, biases).astype(np.float64)


def _read_only(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


class KoopmanModel(LiftedLinearModel):
    """Deep Koopman lifted linear model: rho(x) = [rho_e((x - x_mean) / x_std), 1] (module docstring).

    A (n_K, n_K), B (n_K, n_u) physical; enc_weights: list of L arrays (d_{i-1}, d_i) with
    d_0 = n_x, d_L = n_K - n_x - 1; enc_biases: list of L arrays (d_i,); metadata: the
    artifact's JSON metadata (dict); the remaining keyword arguments as for
    :class:`LiftedLinearModel`."""

    activation = ACTIVATION

    def __init__(self, A, B, *, enc_weights: Sequence[np.ndarray], enc_biases: Sequence[np.ndarray],
                 metadata: Mapping[str, Any] | None = None, **kwargs) -> None:
        super().__init__(A, B, **kwargs)
        self.enc_weights = tuple(_read_only(np.array(W, dtype=np.float64)) for W in enc_weights)
        self.enc_biases = tuple(_read_only(np.array(b, dtype=np.float64).reshape(-1)) for b in enc_biases)
        self.metadata = dict(metadata or {})
        if not self.enc_weights or len(self.enc_weights) != len(self.enc_biases):
            raise ValueError("the encoder needs as many weight matrices as bias vectors (at least one)")
        d = self.n_x
        for i, (W, b) in enumerate(zip(self.enc_weights, self.enc_biases), start=1):
            if W.ndim != 2 or W.shape[0] != d or b.shape != (W.shape[1],):
                raise ValueError(f"encoder layer {i}: expected W ({d}, d) and b (d,), got {W.shape}, {b.shape}")
            d = W.shape[1]
        if self.n_K != self.n_x + d + 1:
            raise ValueError(f"n_K = {self.n_K} must equal n_x + n_encoder + 1 = {self.n_x + d + 1}")
        # The encoder runs in float32, the precision it was trained in (vflpcd.training.train_koopman):
        # its outputs differ from a float64 evaluation by ~1e-7, and it costs a third of the time.
        # The weights are read-only, so these copies cannot fall out of step with them.
        self._w32 = [W.astype(np.float32) for W in self.enc_weights]
        self._b32 = [b.astype(np.float32) for b in self.enc_biases]
        #: the encoder packed for ``encoder_kernel.encoder_loop`` (weights, biases, the widths d_0 .. d_L)
        self.packed_encoder = (np.concatenate([W.ravel() for W in self._w32]), np.concatenate(self._b32),
                               np.array([self.n_x] + [W.shape[1] for W in self._w32], dtype=np.int64))
        self._encoder_loop = None

    def compile_encoder(self, loop) -> None:
        """Run the encoder by ``loop``, ``encoder_kernel.encoder_loop`` compiled (the same bits as its
        numpy layers, which run without one: None, where numba is missing)."""
        self._encoder_loop = loop

    @property
    def n_encoder(self) -> int:
        """n_e, the number of encoder outputs (n_K - n_x - 1)."""
        return int(self.enc_weights[-1].shape[1])

    def encode(self, x: np.ndarray) -> np.ndarray:
        """rho_e of the normalised state: x (..., n_x) window frame -> (..., n_e)."""
        x_n = self.normalise_state(x)
        if self._encoder_loop is None:
            return encoder_forward(x_n, self._w32, self._b32)
        h = np.ascontiguousarray(x_n.reshape(-1, self.n_x), dtype=np.float32)
        out = np.empty((len(h), self.n_encoder))
        dims = self.packed_encoder[2]
        self._encoder_loop(h, *self.packed_encoder, np.empty((2, len(h), int(dims.max())), np.float32), out, 0)
        return out.reshape(x_n.shape[:-1] + (self.n_encoder,))

    def rho(self, x: np.ndarray) -> np.ndarray:
        x = np.asarray(x, dtype=np.float64)
        out = np.empty(x.shape[:-1] + (self.n_encoder + 1,))
        out[..., :-1] = self.encode(x)
        out[..., -1] = 1.0
        return out

    def lifter(self, rows: int) -> "BufferedLift":
        return BufferedLift(self, rows)


class BufferedLift(Lifter):
    """``KoopmanModel.lift`` of ``rows`` states (rows, n_x) at a time; ``encoder`` hands a compiled lift
    (``tick_kernel.window_lift_loop``) the encoder packed for ``encoder_kernel.encoder_loop``, with its
    work arrays for ``rows`` states, allocated once."""

    def __init__(self, model: KoopmanModel, rows: int) -> None:
        super().__init__(model)
        self.n_x, self.n_K = model.n_x, model.n_K
        self._w, self._b = model._w32, model._b32
        dims = model.packed_encoder[2]
        self._packed = (*model.packed_encoder, np.empty((2, rows, int(dims.max())), np.float32))

    def from_normalised(self, x: np.ndarray, normalised: np.ndarray) -> np.ndarray:
        """The lift of states x (rows, n_x) whose normalised states (float32) are at hand."""
        U = np.empty((len(x), self.n_K))
        U[:, : self.n_x] = x
        U[:, self.n_x:-1] = encoder_layers(normalised, self._w, self._b)
        U[:, -1] = 1.0
        return U

    def encoder(self) -> tuple:
        return self._packed
