"""One test view of the include-DC ablation (paper Fig. 10): photo, AC-only SHAC-PCA, PCA over [DC | AC].

    python scripts/ablation_include_dc_view.py SCENE.ply CAMERAS.json IMAGES_DIR OUT.png
        [--rate-point paper_table3:rp4] [--er 0.97] [--view 0] [--test-every 8]

Encodes the scene twice at the rate point (SHAC-PCA at ``--er`` on the AC coefficients, and
with ``include_dc``), decodes, renders test view ``--view`` (every ``--test-every``-th camera
in name order) and writes photo | AC-only | include-DC side by side with each render's PSNR
against the photo (resized to the camera size with INTER_AREA) in the title (a 192-colour PNG).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("ply")
    parser.add_argument("cameras")
    parser.add_argument("images")
    parser.add_argument("out", type=Path)
    parser.add_argument("--rate-point", default="paper_table3:rp4")
    parser.add_argument("--er", type=float, default=0.97)
    parser.add_argument("--view", type=int, default=0)
    parser.add_argument("--test-every", type=int, default=8)
    args = parser.parse_args(argv)

    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from gscodec_shac.codec import Decoder, Encoder
    from gscodec_shac.io.cameras import load_cameras
    from gscodec_shac.io.ply import read_ply
    from gscodec_shac.metrics import psnr
    from gscodec_shac.render import Renderer

    cloud = read_ply(args.ply)
    camera = sorted(load_cameras(args.cameras), key=lambda c: c.name)[:: args.test_every][args.view]
    photo_path = next(p for p in Path(args.images).iterdir() if p.stem == Path(camera.name).stem)
    photo = cv2.cvtColor(cv2.imread(str(photo_path)), cv2.COLOR_BGR2RGB)
    photo = cv2.resize(photo, (camera.width, camera.height), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
    panels = [("photo", photo)]
    for label, include_dc in (("AC-only PCA", False), ("PCA over [DC | AC]", True)):
        stream = Encoder(args.rate_point, sh_stage="pca", workers=1,
                         sh_params={"energy_retention": args.er, "include_dc": include_dc}).encode(cloud)
        image = Renderer(Decoder(workers=1).decode(stream.to_bytes())).render(camera).image
        panels.append((f"{label}, ER {args.er:g}\n{len(stream.to_bytes()) / 1e6:.2f} MB, {psnr(image, photo):.2f} dB",
                       image))
    fig, axes = plt.subplots(1, 3, figsize=(9, 2.6))
    for ax, (title, image) in zip(axes, panels):
        ax.imshow(np.clip(image, 0, 1))
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=90)
    plt.close(fig)
    from PIL import Image

    Image.open(args.out).convert("RGB").quantize(colors=192, method=Image.Quantize.MEDIANCUT).save(args.out, optimize=True)
    print(f"wrote {args.out} ({camera.name})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
