"""``msdnet-infer``: the command and its modes (files, --workers, --dataset, bags, Ray)."""
