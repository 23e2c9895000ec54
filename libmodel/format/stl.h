// STL input and output: the surfaces between the pipeline's stages
// (surface -> remesh) and the runtime's static collision meshes (a scene's
// fluid colliders).
#pragma once

#include "libmodel/format/model.h"

#include <string>

namespace orthosim {

// Reads a binary or ASCII STL file (detected from the content, not the name)
// and welds vertices with bit-identical coordinates, so a closed surface
// written by `orthosim surface` comes back closed. Coordinates are taken as
// metres. Throws Error(path, ...) when the file is missing, truncated or not STL.
Surface read_stl(const std::string& path);
// Writes a binary STL (float32) atomically, `header` (at most 79 characters
// kept) in its 80-byte header. Throws Error(path, ...).
void write_stl(const std::string& path, const Surface& s, const std::string& header = "orthosim binary STL, metres");

}  // namespace orthosim
