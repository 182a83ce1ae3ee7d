import sys, importlib.util
base = sys.argv.pop(1)
spec = importlib.util.spec_from_file_location("warpgauss", f"{base}/warpgauss/__init__.py", submodule_search_locations=[f"{base}/warpgauss", base])
mod = importlib.util.module_from_spec(spec); sys.modules["warpgauss"] = mod; spec.loader.exec_module(mod)
from warpgauss.cli.main import app
sys.argv[0] = "warpgauss"
app()
