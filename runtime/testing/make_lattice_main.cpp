// orthosim_lattice: writes the layered lattice block of runtime/testing/lattice.h
// as a model file, for `orthosim run` and the sample scenes.
//   orthosim_lattice OUT.h5 [--size NUxNVxLAYERS] [--extras]
#include "runtime/testing/lattice.h"

#include <cstdio>
#include <cstring>
#include <iostream>
#include <string>

int main(int argc, char** argv) {
  using namespace orthosim::runtime::testing;
  std::string out;
  int nu = 39, nv = 9, layers = 4;
  bool extras = false;
  for (int i = 1; i < argc; ++i) {
    const std::string a = argv[i];
    if (a == "--size" && i + 1 < argc) {
      if (std::sscanf(argv[++i], "%dx%dx%d", &nu, &nv, &layers) != 3 || nu < 2 || nv < 2 || layers < 2) {
        std::cerr << "orthosim_lattice: error: --size needs NUxNVxLAYERS, each >= 2\n";
        return 2;
      }
    } else if (a == "--extras") {
      extras = true;
    } else if (a == "-h" || a == "--help") {
      std::cout << "usage: orthosim_lattice OUT.h5 [--size NUxNVxLAYERS] [--extras]\n";
      return 0;
    } else if (out.empty() && a[0] != '-') {
      out = a;
    } else {
      std::cerr << "orthosim_lattice: error: unexpected argument '" << a << "'\n";
      return 2;
    }
  }
  if (out.empty()) {
    std::cerr << "orthosim_lattice: error: usage: orthosim_lattice OUT.h5 [--size NUxNVxLAYERS] [--extras]\n";
    return 2;
  }
  try {
    const LayeredBlock b = make_layered_block(nu, nv, layers);
    write_model_file(out, b, extras);
    std::cout << out << ": " << b.n_nodes << " nodes, " << b.layers.size() << " layers\n";
  } catch (const std::exception& e) {
    std::cerr << "orthosim_lattice: error: " << e.what() << "\n";
    return 2;
  }
  return 0;
}
