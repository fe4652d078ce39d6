import pytest
import torch
import torch.nn.functional as F

from ruslam.models.netvlad import NetVLAD


def reference_netvlad(x, weight, bias, centroids):
    """Loop-per-cluster NetVLAD written from the paper's equation, for one image [C, h, w]."""
    feats = F.normalize(x.flatten(1).T, dim=1)  # [N, C]
    logits = feats @ weight.T + bias  # [N, K]
    a = logits.softmax(dim=1)
    blocks = []
    for k in range(len(centroids)):
        v = (a[:, k : k + 1] * (feats - centroids[k])).sum(0)
        blocks.append(v / v.norm())
    out = torch.cat(blocks)
    return out / out.norm()


def test_netvlad_matches_the_per_cluster_equation():
    torch.manual_seed(0)
    layer = NetVLAD(num_clusters=5, dim=12)
    torch.nn.init.normal_(layer.conv.bias)
    x = torch.randn(2, 12, 6, 7)
    out = layer(x)
    assert out.shape == (2, 60)
    w, b = layer.conv.weight[:, :, 0, 0], layer.conv.bias
    for i in range(2):
        torch.testing.assert_close(out[i], reference_netvlad(x[i], w, b, layer.centroids), atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(out.norm(dim=1), torch.ones(2))
    # intra-normalization: every cluster block has the same norm before the final L2
    block_norms = out.view(2, 5, 12).norm(dim=2)
    torch.testing.assert_close(block_norms, torch.full((2, 5), 5**-0.5), atol=1e-5, rtol=1e-4)


def test_init_from_centroids_gives_hard_vlad_and_gradients_flow():
    torch.manual_seed(1)
    centres = F.normalize(torch.randn(3, 8), dim=1)
    layer = NetVLAD(num_clusters=3, dim=8)
    layer.init_from_centroids(centres, alpha=1000.0)
    # 4 locations near centre 0, 2 near centre 2, none near centre 1
    pts = torch.cat([centres[0] + 0.05 * torch.randn(4, 8), centres[2] + 0.05 * torch.randn(2, 8)])
    x = pts.T.reshape(1, 8, 2, 3).clone().requires_grad_(True)
    out = layer(x).view(3, 8)
    unit = F.normalize(pts, dim=1)
    expect0 = F.normalize((unit[:4] - centres[0]).sum(0), dim=0)
    expect2 = F.normalize((unit[4:] - centres[2]).sum(0), dim=0)
    scale = out[0].norm()
    torch.testing.assert_close(out[0] / scale, expect0, atol=1e-3, rtol=1e-3)
    torch.testing.assert_close(out[2] / out[2].norm(), expect2, atol=1e-3, rtol=1e-3)
    layer(x).sum().backward()
    assert x.grad is not None and x.grad.abs().sum() > 0


def test_netvlad_rejects_wrong_channels():
    with pytest.raises(ValueError, match=r"features \[B, 16, h, w\]"):
        NetVLAD(4, 16)(torch.rand(1, 8, 4, 4))


# ---- NetVLAD teacher (VGG16 + NetVLAD + WPCA), pytorch-NetVLAD / Patch-NetVLAD checkpoint layout ----
VGG_CONVS = [0, 2, 5, 7, 10, 12, 14, 17, 19, 21, 24, 26, 28]  # conv layers of VGG16 features up to conv5_3


def patch_netvlad_state(num_clusters=4, pca_dim=16, seed=0):
    import torchvision

    g = torch.Generator().manual_seed(seed)
    vgg = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])  # VGG16 features
    state = {}
    for i in VGG_CONVS:
        state[f"encoder.{i}.weight"] = torch.randn(vgg[i].weight.shape, generator=g) * 0.05
        state[f"encoder.{i}.bias"] = torch.randn(vgg[i].bias.shape, generator=g) * 0.01
    state["pool.conv.weight"] = torch.randn(num_clusters, 512, 1, 1, generator=g)
    state["pool.centroids"] = torch.randn(num_clusters, 512, generator=g)
    state["WPCA.0.weight"] = torch.randn(pca_dim, num_clusters * 512, 1, 1, generator=g)
    state["WPCA.0.bias"] = torch.randn(pca_dim, generator=g)
    return state


def test_netvlad_teacher_loads_the_public_layout_and_computes_the_pipeline(tmp_path):
    import torchvision

    from ruslam.models.pretrained.netvlad import NetVLADTeacher

    state = patch_netvlad_state()
    path = tmp_path / "pittsburgh_WPCA16.pth.tar"
    torch.save({"state_dict": state}, path)
    teacher = NetVLADTeacher(weights=str(path), num_clusters=4, pca_dim=16)
    image = torch.rand(2, 3, 64, 80, generator=torch.Generator().manual_seed(1))
    out = teacher(image)
    assert out.shape == (2, 16)
    # the same pipeline by hand: ImageNet-normalized VGG16 conv5_3 (no last ReLU), per-cluster VLAD, WPCA, L2
    vgg = torchvision.models.vgg.make_layers(torchvision.models.vgg.cfgs["D"])[:29]
    vgg.load_state_dict({k.removeprefix("encoder."): v for k, v in state.items() if k.startswith("encoder.")})
    mean, std = torch.tensor([0.485, 0.456, 0.406]), torch.tensor([0.229, 0.224, 0.225])
    with torch.no_grad():
        feats = vgg((image - mean[:, None, None]) / std[:, None, None])
    w = state["pool.conv.weight"][:, :, 0, 0]
    for i in range(2):
        vlad = reference_netvlad(feats[i], w, torch.zeros(4), state["pool.centroids"])
        pca = state["WPCA.0.weight"][:, :, 0, 0] @ vlad + state["WPCA.0.bias"]
        torch.testing.assert_close(out[i], pca / pca.norm(), atol=1e-4, rtol=1e-3)


def test_netvlad_teacher_names_missing_weights(tmp_path):
    from ruslam.models.pretrained.netvlad import NetVLADTeacher

    state = patch_netvlad_state()
    del state["WPCA.0.bias"]
    path = tmp_path / "partial.pth"
    torch.save(state, path)
    with pytest.raises(ValueError, match=r"missing keys \['WPCA.0.bias'\]"):
        NetVLADTeacher(weights=str(path), num_clusters=4, pca_dim=16)
    with pytest.raises(FileNotFoundError, match="needs user-supplied weights"):
        NetVLADTeacher(num_clusters=4, pca_dim=16)
