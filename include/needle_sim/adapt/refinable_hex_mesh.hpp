#pragma once
// A hexahedral mesh refined by the 1 -> 8 template (paper §2.3, Fig. "hexa template"),
// nested, with hanging nodes and 2:1 balance across faces and edges (doc/method.md).
//
// Cells form a forest over the coarse mesh; the leaves are the active elements. New nodes
// are shared through the edges and faces that create them (an edge midpoint is the same
// node for every cell around that edge), and their rest positions come from the trilinear
// map of the parent, so refining never moves material. A node in the middle of an active
// leaf's edge (face) that other, finer leaves use is hanging: it follows the edge's two (the
// face's four) corners with weights 1/2 (1/4). Coarsening merges eight leaf siblings back.
#include <array>
#include <map>
#include <vector>

#include "needle_sim/core/types.hpp"
#include "needle_sim/fem/hex_mesh.hpp"

namespace needle_sim {

class RefinableHexMesh {
 public:
  explicit RefinableHexMesh(const HexMesh& coarse);

  // The active mesh: nodes used by active leaves (compact numbering), leaves as elements.
  struct Active {
    HexMesh mesh;
    std::vector<int> level;             // per element
    std::vector<int> cell;              // per element: the forest cell it is
    std::vector<int> node_id;           // per active node: id in the forest
    // Per active node: masters (active node indices) and weights; empty if not hanging.
    std::vector<std::vector<std::pair<int, double>>> hanging;
    int numHanging() const;
  };
  Active active() const;

  // Refines the given leaf cells, and as many others as the 2:1 balance requires.
  // Returns the number of cells refined.
  int refine(const std::vector<int>& cells);
  // Merges the children of the given cells back, where all eight are leaves and the
  // balance allows it. Returns the number of cells coarsened.
  int coarsen(const std::vector<int>& parents);

  int numCells() const { return static_cast<int>(cells_.size()); }
  bool isLeaf(int c) const { return cells_[c].child < 0; }
  // A leaf whose ancestors are all refined (children merged back by coarsening are not).
  bool isActive(int c) const {
    return cells_[c].child < 0 && (cells_[c].parent < 0 || cells_[cells_[c].parent].child >= 0);
  }
  int level(int c) const { return cells_[c].level; }
  int parent(int c) const { return cells_[c].parent; }
  int numLeaves() const;
  const Vec3& node(int id) const { return nodes_[id]; }
  int numNodes() const { return static_cast<int>(nodes_.size()); }
  int numActiveNodes() const;
  // A refinement node is the average of these nodes (an edge's 2 ends, a face's 4 corners, a
  // cell's 8 corners), which is also the parent's trilinear field there: any nodal field is
  // carried to new nodes by averaging, and their ids are larger than their sources'.
  const std::vector<int>& sources(int id) const { return sources_[id]; }
  bool nodeActive(int id) const { return activeNode(id); }

 private:
  struct Cell {
    std::array<int, 8> nodes;
    int level = 0;
    int parent = -1;
    int child = -1;  // first of 8 consecutive children, -1 for a leaf
    int centre = -1; // body-centre node, kept for re-refinement
    int former = -1; // children merged back by coarsening, reused when refined again
  };
  int edgeMid(int a, int b, bool create);
  int faceMid(const std::array<int, 4>& f, bool create);
  void split(int c);
  bool violatesBalance(int c) const;
  bool activeNode(int id) const { return id >= 0 && use_[id] > 0; }
  int findEdgeMid(int a, int b) const;
  int findFaceMid(std::array<int, 4> f) const;

  std::vector<Vec3> nodes_;
  std::vector<int> use_;  // active leaves using each node
  std::vector<std::vector<int>> sources_;
  std::vector<Cell> cells_;
  std::map<std::pair<int, int>, int> edge_mid_;
  std::map<std::array<int, 4>, int> face_mid_;
};

}  // namespace needle_sim
