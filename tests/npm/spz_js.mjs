// node spz_js.mjs SOURCE TARGET: convert between .ply and .spz with spz-js, as its README does
import { createReadStream, readFileSync, writeFileSync } from 'fs';
import { Readable } from 'stream';
import { loadPly, loadSpz, serializePly, serializeSpz } from 'spz-js';

const [source, target] = process.argv.slice(2);
const gaussians = source.endsWith('.spz')
    ? await loadSpz(readFileSync(source))
    : await loadPly(Readable.toWeb(createReadStream(source)));
writeFileSync(target, Buffer.from(target.endsWith('.spz') ? await serializeSpz(gaussians) : serializePly(gaussians)));
