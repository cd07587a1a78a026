//! Edge adjacency of a welded triangle mesh, for silhouette detection in `antialias`.

use super::check_faces;
use crate::error::Result;

/// For every face `f` and edge `k` (the edge opposite vertex `k`, i.e. between vertices
/// `k+1` and `k+2`), the other face sharing that edge, or −1 when the edge is on the
/// boundary, shared by more than two faces (non-manifold), or belongs to a degenerate face
/// (a repeated index). `(F, 3)`, int32.
pub fn edge_topology(faces: &[i32], num_verts: usize) -> Result<Vec<i32>> {
    let num_faces = check_faces("faces", faces, num_verts, "V")?;
    let mut edges: Vec<(u64, u32)> = Vec::with_capacity(3 * num_faces);
    for (f, t) in faces.chunks_exact(3).enumerate() {
        if t[0] == t[1] || t[1] == t[2] || t[2] == t[0] {
            continue;
        }
        for k in 0..3 {
            let (a, b) = (t[(k + 1) % 3] as u64, t[(k + 2) % 3] as u64);
            edges.push(((a.min(b) << 32) | a.max(b), (3 * f + k) as u32));
        }
    }
    // Unique (key, slot) pairs: the order, and so the result, is fully determined.
    edges.sort_unstable();
    let mut neighbour = vec![-1i32; 3 * num_faces];
    let mut i = 0;
    while i < edges.len() {
        let mut j = i + 1;
        while j < edges.len() && edges[j].0 == edges[i].0 {
            j += 1;
        }
        if j - i == 2 {
            let (s, t) = (edges[i].1 as usize, edges[i + 1].1 as usize);
            neighbour[s] = (t / 3) as i32;
            neighbour[t] = (s / 3) as i32;
        }
        i = j;
    }
    Ok(neighbour)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn square_of_two_triangles() {
        // 3---2
        // | / |
        // 0---1
        let faces = [0, 1, 2, 0, 2, 3];
        let topo = edge_topology(&faces, 4).unwrap();
        // Face 0's edge opposite vertex 1 is (2, 0), shared with face 1; face 1's edge
        // opposite vertex 3 is (0, 2), shared with face 0.
        assert_eq!(topo, vec![-1, 1, -1, -1, -1, 0]);
    }

    #[test]
    fn non_manifold_and_degenerate_edges_are_open() {
        let faces = [0, 1, 2, 1, 0, 3, 0, 1, 4, 5, 5, 6];
        let topo = edge_topology(&faces, 7).unwrap();
        assert_eq!(topo[2], -1); // edge (0, 1) has three faces
        assert_eq!(&topo[9..], &[-1, -1, -1]);
    }
}
