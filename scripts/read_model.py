#!/usr/bin/python3
"""Summarises an orthosim model file with h5py: the Python reading example of docs/model-format.md."""
import sys

import h5py


def main(path):
    with h5py.File(path, "r") as f:
        if "orthosim_format" not in f.attrs:
            sys.exit(f"{path}: not an orthosim model file")
        print(f"{path}: orthosim format {f.attrs['orthosim_format']}")
        if "volume" in f:
            labels = f["volume/labels"]
            print(f"  volume {labels.shape[::-1]} voxels (x, y, z), spacing_m {list(f['volume'].attrs['spacing_m'])}")
        for name, layer in f.get("layers", {}).items():
            if name == "sets":
                continue
            nodes = layer["nodes"][:]
            print(f"  layer {name}: {layer.attrs['kind']}, {nodes.shape[0]} nodes "
                  f"[{layer['nodes'].attrs['unit']}], {layer['springs'].shape[0]} springs, "
                  f"mass {layer['masses'][:].sum():.4g} kg")
        for kind in ("surfaces", "quads", "vessels", "tuning"):
            for name, group in f.get(kind, {}).items():
                print(f"  {kind}/{name}: " + ", ".join(f"{k} {v.shape}" for k, v in group.items()))


if __name__ == "__main__":
    if len(sys.argv) != 2:
        sys.exit("usage: read_model.py MODEL.h5")
    main(sys.argv[1])
