"""VLAD over the local teacher's dense descriptors: the offline global teacher (no NetVLAD weights needed).

Codebook: k-means (K=64, seeded, `scipy.cluster.vq.kmeans2` with k-means++) on dense descriptors of a sample
of training images. Aggregation (Jegou et al. 2010; Arandjelovic & Zisserman 2013): hard-assign each location to
its nearest centre, sum the residuals per centre, intra-normalize each centre's block, signed power-law, L2.
K x D = 64 x 64 = 4096-d for XFeat. The codebook hash enters the teacher fingerprint, hence the cache key.

A small codebook fitted on the embedded procedural images ships in the package (`PACKAGED_XFEAT_CODEBOOK`) so
that ``load_extractor("xfeat")`` returns a global descriptor out of the box; refit it with
``python -m ruslam.models.pretrained.vlad`` (see `main`).
"""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy.cluster.vq import kmeans2

from ruslam.atomic_files import atomic_path
from ruslam.data.rgbd_sample import sample_image
from ruslam.errors import InputError, MissingInput

PACKAGED_XFEAT_CODEBOOK = Path(__file__).with_name("vlad_xfeat_k64.npy")


def fit_codebook(descriptors: np.ndarray, num_clusters: int = 64, seed: int = 0, iterations: int = 25) -> np.ndarray:
    """k-means centres [K, D] (float32) of descriptors [N, D]; deterministic for a given seed."""
    descriptors = np.asarray(descriptors, dtype=np.float64)
    if descriptors.ndim != 2 or len(descriptors) < num_clusters:
        raise InputError(
            f"k-means needs at least {num_clusters} descriptors as an [N, D] array, got shape {descriptors.shape}."
        )
    centres, _ = kmeans2(descriptors, num_clusters, iter=iterations, minit="++", seed=seed)
    return centres.astype(np.float32)


def load_codebook(path: str | Path, num_clusters: int, dim: int) -> np.ndarray:
    path = Path(path)
    if not path.is_file():
        raise MissingInput(f"VLAD codebook {path} does not exist.")
    try:
        codebook = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as err:
        raise InputError(f"VLAD codebook {path} is not a readable .npy array ({err}).") from None
    if codebook.shape != (num_clusters, dim) or not np.isfinite(codebook).all():
        raise InputError(f"VLAD codebook {path} has shape {codebook.shape}, expected finite ({num_clusters}, {dim}).")
    return codebook.astype(np.float32)


def save_codebook(codebook: np.ndarray, path: str | Path) -> None:
    """Write atomically (temp file + rename): a crash never leaves a truncated codebook."""
    with atomic_path(path) as tmp:
        np.save(tmp, np.ascontiguousarray(codebook, dtype=np.float32))


def vlad_aggregate(dense: torch.Tensor, codebook: torch.Tensor, power: float = 0.5) -> torch.Tensor:
    """dense descriptors [B, D, h, w], codebook [K, D] -> VLAD [B, K*D], intra-normalized, power-law, L2."""
    b, d, _, _ = dense.shape
    k = codebook.shape[0]
    x = dense.flatten(2).transpose(1, 2).float()  # [B, N, D]
    assign = torch.cdist(x, codebook[None].expand(b, -1, -1)).argmin(dim=2)  # [B, N]
    sums = torch.zeros(b, k, d, dtype=x.dtype, device=x.device).scatter_add_(1, assign[..., None].expand(-1, -1, d), x)
    counts = torch.zeros(b, k, dtype=x.dtype, device=x.device).scatter_add_(1, assign, torch.ones_like(x[..., 0]))
    residuals = sums - counts[..., None] * codebook  # sum over members of (x - c_k)
    v = F.normalize(residuals, dim=2)  # intra-normalization (empty clusters stay zero)
    v = v.sign() * v.abs().pow(power)
    return F.normalize(v.flatten(1), dim=1)


class VLAD(nn.Module):
    """Global head of the offline teacher: `forward(image, local_outputs)` -> [B, K*D] from the dense descriptors.

    `codebook`: a .npy path, "packaged" (the shipped XFeat codebook, `PACKAGED_XFEAT_CODEBOOK`, 64 x 64), or None
    to fit one on the training images when the cache is built (`prepare`).
    """

    def __init__(
        self,
        num_clusters: int = 64,
        dim: int = 64,
        codebook: str | None = None,
        power: float = 0.5,
        fit_images: int = 64,
        fit_descriptors_per_image: int = 400,
        seed: int = 0,
    ):
        super().__init__()
        self.num_clusters, self.dim, self.power, self.seed = num_clusters, dim, power, seed
        self.fit_images, self.fit_descriptors_per_image = fit_images, fit_descriptors_per_image
        self.register_buffer("codebook", torch.zeros(num_clusters, dim))
        if codebook == "packaged":
            codebook = PACKAGED_XFEAT_CODEBOOK
        if codebook is not None:
            self.set_codebook(load_codebook(codebook, num_clusters, dim))

    @property
    def output_dim(self) -> int:
        return self.num_clusters * self.dim

    @property
    def fitted(self) -> bool:
        return bool(self.codebook.any())

    def set_codebook(self, codebook: np.ndarray) -> None:
        self.codebook.copy_(torch.as_tensor(codebook, dtype=torch.float32))

    def codebook_hash(self) -> str:
        return hashlib.sha256(self.codebook.cpu().numpy().astype(np.float32).tobytes()).hexdigest()

    def forward(self, image: torch.Tensor, local_outputs: dict[str, torch.Tensor]) -> torch.Tensor:
        if not self.fitted:
            raise RuntimeError("The VLAD codebook is not fitted: pass codebook=<.npy path> or build the cache first.")
        dense = local_outputs["dense_descriptors"]
        if dense.shape[1] != self.dim:
            raise ValueError(f"VLAD codebook is {self.dim}-d but the dense descriptors are {dense.shape[1]}-d.")
        return vlad_aggregate(dense, self.codebook.to(dense.device), self.power)

    @torch.no_grad()
    def prepare(self, local: nn.Module, dataset, cache_dir: str | Path) -> None:
        """Load the codebook saved beside the cache, or fit it on a seeded sample of `dataset` and save it there."""
        if self.fitted:
            return
        path = Path(cache_dir) / f"vlad_codebook_k{self.num_clusters}_seed{self.seed}.npy"
        if path.is_file():
            self.set_codebook(load_codebook(path, self.num_clusters, self.dim))
            return
        images = (sample_image(dataset[int(i)]) for i in sample_indices(len(dataset), self.fit_images, self.seed))
        descriptors = dense_descriptor_sample(local, images, self.fit_descriptors_per_image, self.seed)
        self.set_codebook(fit_codebook(descriptors, self.num_clusters, self.seed))
        save_codebook(self.codebook.numpy(), path)



def sample_indices(n: int, count: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.sort(rng.choice(n, size=min(count, n), replace=False))


@torch.no_grad()
def dense_descriptor_sample(local: nn.Module, images, per_image: int, seed: int) -> np.ndarray:
    """Run the local teacher on HxWx3 float images; return up to `per_image` random dense descriptors of each."""
    rng = np.random.default_rng(seed)
    chunks = []
    for image in images:
        x = torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32)).permute(2, 0, 1)[None]
        dense = local(x)["dense_descriptors"][0].flatten(1).T.cpu().numpy()
        chunks.append(dense[rng.choice(len(dense), size=min(per_image, len(dense)), replace=False)])
    if not chunks:
        raise ValueError("Cannot fit a VLAD codebook on an empty dataset.")
    return np.concatenate(chunks)


def main() -> None:
    """Refit the packaged XFeat codebook on embedded procedural images (the recorded recipe of the shipped file)."""
    from ruslam.data.procedural import ProceduralRGBD  # noqa: PLC0415
    from ruslam.models.pretrained.xfeat import XFeatTeacher  # noqa: PLC0415

    torch.manual_seed(0)
    dataset = ProceduralRGBD(num_images=200, height=240, width=320, seed=1234)
    descriptors = dense_descriptor_sample(XFeatTeacher(), (dataset[i]["image"] for i in range(len(dataset))), 400, 0)
    save_codebook(fit_codebook(descriptors, 64, seed=0), PACKAGED_XFEAT_CODEBOOK)
    print(f"wrote {PACKAGED_XFEAT_CODEBOOK} from {len(descriptors)} descriptors of {len(dataset)} images")


if __name__ == "__main__":
    main()
