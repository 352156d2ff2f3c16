"""Map the root folders onto the ``msdnet`` namespace: ``runtime/`` -> ``msdnet.runtime`` etc.

Everything else (metadata, dependencies, scripts) lives in pyproject.toml.
"""

from setuptools import find_packages, setup

ROOTS = {
    "runtime": "msdnet.runtime",
    "training": "msdnet.training",
    "export": "msdnet.export",
    "benchmarks": "msdnet.benchmarks",
    "models": "msdnet.models",  # bundled exported models (data only)
}

packages: list[str] = []
package_dir: dict[str, str] = {}
for folder, name in ROOTS.items():
    packages.append(name)
    package_dir[name] = folder
    for sub in find_packages(folder):
        packages.append(f"{name}.{sub}")
        package_dir[f"{name}.{sub}"] = f"{folder}/{sub.replace('.', '/')}"

setup(
    packages=packages,
    package_dir=package_dir,
    package_data={
        "msdnet.runtime": ["py.typed"],
        "msdnet.models": ["*/*.onnx", "*/*.json", "*/*.md"],
    },
)
