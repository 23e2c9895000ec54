// Lazy loading of a runtime Model from an orthosim model file.
//
// Only what a scene names is read:
// - for each requested layer: nodes, masses and the linear decomposition
//   lin_springs, lin_rest_length, lin_k, lin_damping, lin_slack; quads only
//   when `surface` is set (the scene writes surfaces); tets when the layer
//   has a volume_modulus or a guard_modulus (its volume term and inversion guard, Model::tet);
// - the requested node sets /layers/sets/<name>;
// - the requested vessels (nodes, radii, edges of /vessels/<name>);
// - with `couple_unloaded`, the lin_springs index array of every other layer
//   (to find springs that reach the loaded nodes; their parameters are read
//   only if some do), and the nodes of the layers owning the far ends of
//   those springs: such ends become anchors, fixed at their rest positions.
// Nothing else is opened: no /volume, /surfaces, /quads, /vessels not named,
// /tuning, the original biphasic spring fields, tets of layers without a
// volume term. Layer extents come
// from attributes and dataset shapes, which read no data.
// h5::File::stats() on the reader counts what was read.
#pragma once

#include "libmodel/format/model.h"
#include "runtime/model.h"

#include <string>
#include <vector>

namespace orthosim::runtime {

struct LoadRequest {
  std::vector<std::string> layers;     // names under /layers; empty = every layer
  std::vector<std::string> node_sets;  // names under /layers/sets
  std::vector<std::string> vessels;    // names under /vessels
  bool surface = false;                // read the loaded layers' quads
  bool vessel_tubes = false;           // read the named vessels' tube surfaces (output only)
  bool couple_unloaded = true;         // anchor springs of other layers that reach loaded nodes
};

// What a model file offers, from its group structure only (no dataset read).
struct ModelIndex {
  std::vector<std::string> layers;     // sorted
  std::vector<std::string> node_sets;  // sorted
  std::vector<std::string> vessels;    // sorted
};
ModelIndex index_model(const ModelReader& r);

// Throws Error(r.path(), ...) when a requested name is absent or the data
// are invalid (shapes, ids out of range, negative masses or stiffnesses...).
Model load_model(const ModelReader& r, const LoadRequest& req);

}  // namespace orthosim::runtime
