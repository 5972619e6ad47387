#pragma once
// Disjoint sets over 0..n-1 (path halving; the smaller index is the root, so the
// roots do not depend on the order of the unions).
#include <algorithm>
#include <cstddef>
#include <numeric>
#include <vector>

namespace station {

struct UnionFind {
  std::vector<int> parent;
  explicit UnionFind(std::size_t n = 0) : parent(n) { std::iota(parent.begin(), parent.end(), 0); }
  /// A new singleton set; its index.
  int add() {
    parent.push_back(int(parent.size()));
    return parent.back();
  }
  int find(int x) {
    while (parent[std::size_t(x)] != x) x = parent[std::size_t(x)] = parent[std::size_t(parent[std::size_t(x)])];
    return x;
  }
  void unite(int a, int b) {
    a = find(a);
    b = find(b);
    if (a != b) parent[std::size_t(std::max(a, b))] = std::min(a, b);
  }
};

}  // namespace station
